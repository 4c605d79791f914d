import os
import sys
from pathlib import Path

# One BLAS thread per process: the suite's matrices are small and several processes (dask
# workers, uvicorn servers, subprocess CLIs) run at once; multi-threaded OpenBLAS on 2 shared
# cores was measured 10x slower. Subprocesses inherit the variables.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

threadpool_limits(limits=1)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# the lab data: $GPNARX_BERT_DATA, then ../shared/data/bert-t5nm (the lookup the code uses, training.datapaths)
from gpnarx.training.datapaths import bert_data_dir  # noqa: E402

BERT_DATA = bert_data_dir()

# The modules that take longest, longest first. pytest-xdist's loadscope hands whole modules to the workers
# in collection order (with its reordering by test count off, pytest_configure below: that put these
# few-test modules last), so the long ones start first and the short ones fill in at the end. The module
# building the session's bert-real registry (bert_real_registry, the longest single build) comes first and
# the other two that read it well after it, so no worker waits on the build.
LONGEST_FIRST = ("test_real_records.py", "test_reproduce_more.py", "test_reproduce.py", "test_estimator.py",
                 "test_bench_smoke.py", "test_bench_smoke_more.py", "test_pipeline.py", "test_wheel.py",
                 "test_dask_cluster.py", "test_first_start.py", "test_deploy.py", "test_faults.py",
                 "test_real_records_more.py", "test_real_monitor.py", "test_registry_remote.py",
                 "test_service_fuzz.py", "test_ui_browser.py", "test_stream.py")


def pytest_configure(config):
    """Under pytest-xdist's loadscope, hand out modules in collection order (``LONGEST_FIRST``), not
    reordered by their number of tests (``--loadscope-reorder``, pytest-xdist's default since 3.6)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    """Run the modules of ``LONGEST_FIRST`` first, in its order; every other module after them in collection
    order, and each module's tests in their own order (a stable sort)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="session", autouse=True)
def _session_cache_root(tmp_path_factory):
    """The cache root of tests/session_cache.py: one folder for the whole session, beside the
    pytest-xdist workers' base folders (their common parent) so every worker builds into the same one."""
    import session_cache

    base = tmp_path_factory.getbasetemp()
    session_cache.set_root((base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "session-cache")


@pytest.fixture(scope="session")
def bert_real_registry(_session_cache_root):
    """A registry folder holding ``bert-real`` trained from its shipped config as the default-registry
    build trains it (``training.pipeline.train``, the report's free runs linearised, no report folder),
    once per session for every module and pytest-xdist worker (tests/session_cache.py), rebuilt when the
    config, the package's source or the data folder's path changes. Read it only: copy it to add bundles."""
    from session_cache import build_once, digest

    from gpnarx.training.defaults import shipped_config
    from gpnarx.training.pipeline import train

    config = shipped_config("bert-real")

    def build(folder: Path) -> None:
        train(config, folder / "registry", report=False, report_method="linear")

    return build_once("bert-real", digest(config, Path(__file__), extra=str(BERT_DATA)), build) / "registry"


@pytest.fixture(scope="session")
def bert_real_model(bert_real_registry):
    """The model of ``bert_real_registry``, its band calibration checked: on the config's 'lags' records,
    every one covered at 99 %."""
    from gpnarx.storage.registry import Registry
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config

    cfg = load_config(shipped_config("bert-real"))
    assert cfg.model["band_calibration"] == "lags"
    m = Registry(bert_real_registry).scan().get("bert-real").model
    d = m.band_discrepancy_  # the band calibration on the config's 'lags' records, as trained
    assert d["records"] == [r.name for r in cfg.records_for("lags")]
    assert d["reached"] and min(d["coverage_after"].values()) >= 0.99
    return m


def sdof_simulate(u, fs=500.0, f_n=20.0, zeta=0.02, mass=1.0):
    """Linear SDOF oscillator (m=1 kg, k=(2 pi 20 Hz)^2 N/m, 2% damping), exact ZOH discretisation."""
    from scipy import signal

    wn = 2 * np.pi * f_n
    A = np.array([[0.0, 1.0], [-wn**2, -2 * zeta * wn]])
    B = np.array([[0.0], [1.0 / mass]])
    Ad, Bd, *_ = signal.cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), 1 / fs, method="zoh")
    x = np.zeros(2)
    y = np.empty(len(u))
    for i, ui in enumerate(u):
        y[i] = x[0]
        x = Ad @ x + Bd[:, 0] * ui
    return y


@pytest.fixture(scope="session")
def sdof_data():
    rng = np.random.default_rng(1)
    u = rng.normal(size=3000)
    y = sdof_simulate(u)
    yn = y + 0.05 * np.std(y) * rng.normal(size=y.size)  # 5% output noise (RMS ratio)
    u2 = rng.normal(size=1500)
    y2 = sdof_simulate(u2)
    return {"u": u, "y": y, "yn": yn, "u2": u2, "y2": y2}


@pytest.fixture(scope="session")
def sdof_model(sdof_data, _session_cache_root):
    """GPNARX (ny = nu = 16, 1500 ML-II rows) fitted on ``sdof_data``'s noisy record, once per session for
    every pytest-xdist worker (tests/session_cache.py: pickled by the first worker, each worker unpickles
    its own copy, the same numbers as a fit of its own)."""
    import pickle

    from session_cache import build_once, digest

    from gpnarx.model.estimator import GPNARX

    def build(folder: Path) -> None:
        model = GPNARX(ny=16, nu=16, max_train_points=1500, n_restarts=0).fit([(sdof_data["u"], sdof_data["yn"])])
        (folder / "model.pkl").write_bytes(pickle.dumps(model))

    folder = build_once("sdof-model", digest(Path(__file__)), build)
    return pickle.loads((folder / "model.pkl").read_bytes())
