"""Install tiers: the core install serves and predicts without the extra train's matplotlib and tqdm, and
a local registry needs no object-storage package (the extra s3's fsspec); the test and lint tools are
dependency groups, which the extra `test` lists again.

A subprocess hides these packages (``sys.modules[name] = None``: every import of them fails, as in a
core install) and then builds a small model, serves it, predicts over HTTP and with the CLI; training
with a report refuses at once with one line naming the extra.
"""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent('''
    import io, json, sys, warnings
    from contextlib import redirect_stderr
    HIDE = ("matplotlib", "tqdm", "fsspec")
    if sys.argv[2] == "hide":
        for name in HIDE:
            sys.modules[name] = None
    import numpy as np
    from fastapi.testclient import TestClient
    from gpnarx.cli.main import main
    from gpnarx.storage.bundle import save_bundle
    from gpnarx.model.estimator import GPNARX
    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    tmp = sys.argv[1]
    rng = np.random.default_rng(0)
    u = rng.standard_normal(400)
    y = np.convolve(u, [0.0, 0.5, 0.25, 0.1])[:400]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GPNARX(ny=2, nu=2, max_train_points=150, n_restarts=0).fit([(u, y)])
    save_bundle(model, tmp + "/reg", "m", fs=100.0, units={"u": "N", "y": "m"})
    c = TestClient(create_app(tmp + "/reg", Settings(workers=1, queue_size=2)))
    r = c.post("/v1/models/m/predict", json={"u": u[:200].tolist(), "fs": 100.0, "mc_paths": 8},
               headers={"accept-encoding": "gzip"})
    out = {"http": r.status_code, "n": len(r.json()["mean"]),
           "imported": sorted(n for n in HIDE if sys.modules.get(n) is not None)}
    np.savez(tmp + "/r.npz", u=u[:200], y=y[:200], fs=100.0)
    err = io.StringIO()
    with redirect_stderr(err):
        out["cli_predict"] = main(["predict", "--registry", tmp + "/reg", "--model", "m", tmp + "/r.npz",
                                   "--mc", "8"])
        if sys.argv[2] == "hide":  # with matplotlib this would train for real: only the refusal is run
            out["cli_train"] = main(["train", "bouc-wen", "--registry", tmp + "/reg2"])
    out["stderr"] = err.getvalue()
    print(json.dumps(out))
''')


def run(tmp_path, mode):
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), mode], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_core_serves_and_predicts_without_matplotlib_and_tqdm(tmp_path):
    out = run(tmp_path, "hide")
    assert out["http"] == 200 and out["n"] == 200
    assert out["cli_predict"] == 0
    # training with a report refuses before any work, naming the extra
    assert out["cli_train"] == 1
    lines = [ln for ln in out["stderr"].splitlines() if "error" in ln]
    assert len(lines) == 1 and "gpnarx[train]" in lines[0], out["stderr"]


def test_serving_does_not_import_the_plotting_stack(tmp_path):
    out = run(tmp_path, "show")
    assert out["http"] == 200 and "matplotlib" not in out["imported"], out
    assert "fsspec" not in out["imported"], out  # a local registry never imports the object-storage stack


def test_pyproject_tiers():
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = " ".join(meta["dependencies"])
    for name in ("matplotlib", "tqdm"):
        assert name not in core
    for name in ("scikit-learn", "joblib", "httpx"):
        assert name in core
    extras = meta["optional-dependencies"]
    assert {"train", "client", "formats", "dask", "s3", "jax", "otel"} <= set(extras)
    assert any("matplotlib" in d for d in extras["train"]) and any("tqdm" in d for d in extras["train"])
    # `pip install -e '.[test]'` keeps everything the tests need: the product's extras they exercise...
    own = [Requirement(r) for r in extras["test"] if Requirement(r).name == "gpnarx"]
    assert len(own) == 1 and {"train", "formats", "s3", "dask", "jax", "otel"} <= own[0].extras


def _group(groups: dict, name: str) -> list[str]:
    """A PEP 735 dependency group with its include-group entries expanded."""
    out = []
    for item in groups[name]:
        out += _group(groups, item["include-group"]) if isinstance(item, dict) else [item]
    return out


def _canonical(reqs) -> list[str]:
    return sorted(str(Requirement(r)) for r in reqs)


def test_tools_are_dependency_groups_and_the_test_extra_lists_them_again():
    """The test and lint tools are the PEP 735 groups `test` and `lint` (`dev` = both); the extra `test`
    lists the same requirements (pip before 25.1 cannot install a group), and no product extra holds one."""
    import tomllib

    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    groups, extras = doc["dependency-groups"], doc["project"]["optional-dependencies"]
    tools = [r for r in extras["test"] if Requirement(r).name != "gpnarx"]
    assert _canonical(tools) == _canonical(_group(groups, "test") + _group(groups, "lint")), (
        "the extra `test` and the dependency groups `test` + `lint` differ: change both")
    assert _canonical(_group(groups, "dev")) == _canonical(tools)
    assert {"pytest", "ruff", "import-linter"} <= {Requirement(r).name for r in tools}
    names = {Requirement(r).name for r in tools}
    for extra, reqs in extras.items():
        if extra != "test":
            assert not names & {Requirement(r).name for r in reqs}, (extra, names)


def test_docs_install_sizes_are_the_render_of_the_stored_run_of_this_lock():
    """docs/deploy.md's install sizes are the render (gpnarx.training.pages.install_sizes) of tools/install_sizes.py's
    stored run docs/runs/install/sizes.json, a run of the Dockerfile's steps on the requirements.lock in force: the
    image's packages are the lock's pins (same versions) and gpnarx; the core holds neither matplotlib nor tqdm, the
    core with `train` holds both."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("install_sizes", ROOT / "tools" / "install_sizes.py")
    sizes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sizes)
    run = json.loads(sizes.RUN.read_text())
    page = (ROOT / "docs" / "deploy.md").read_text()
    block = page[page.index(sizes.BEGIN):page.index(sizes.END) + len(sizes.END)]
    assert block == sizes.render(run), "docs/deploy.md differs from the render: python tools/install_sizes.py --render"
    facts = sizes.dockerfile_facts((ROOT / "Dockerfile").read_text())
    assert (run["base_image"], run["image_spec"]) == (facts["base_image"], facts["spec"])
    image = run["tiers"]["image"]["packages"]
    assert {k: v for k, v in image.items() if k != "gpnarx"} == sizes.locked(), (
        "requirements.lock changed since the stored run: python tools/install_sizes.py")
    core, train = run["tiers"]["core"], run["tiers"]["train"]
    assert not {"matplotlib", "tqdm"} & set(core["packages"]) and {"matplotlib", "tqdm"} <= set(train["packages"])
    assert set(core["packages"]) < set(train["packages"]) < set(image)
    assert 0 < core["site_packages_bytes"] < train["site_packages_bytes"] < run["tiers"]["image"]["site_packages_bytes"]
