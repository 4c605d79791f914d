"""Training and bulk prediction on a real Dask cluster on loopback (issue 26).

Starts ``dask scheduler`` and two ``dask worker`` processes (one thread each) as subprocesses on free
ports, then runs the ``gpnarx`` CLI in child processes twice, once with ``--scheduler`` and once
locally: ``gpnarx train --choose-lags`` (lag surface, free runs and report figures as tasks) must
write a bundle with the same lags and training metrics, and ``gpnarx predict-many`` must write the
same predictions for the same seed. The wall times of both runs are printed (``pytest -s``).

The workers start with a preload that makes reading a config, a record file or a bundle from a
path fail, and run in a folder of their own: everything they compute was sent to them as objects.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

from gpnarx.cli.main import main  # noqa: E402

CONFIG = """
name = "bw-dask"
[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"
[physics]
mass = 2.0
[model]
ny = 2
nu = 2
max_train_points = 300
restarts = 0
[lags]
ny = "2:4:2"
nu = "2:4:2"
[predict]
mc_paths = 32
[novelty]
false_alarm_rate = 0.05
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 1 }
[[records]]
name = "lag-sweep"
roles = ["lags", "verify"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
[[records]]
name = "sine"
roles = ["validate"]
simulate = { system = "bouc-wen", excitation = "sine", amplitude = 30.0, freq = 35.0, duration = 0.5 }
meta = { initial = "measured" }
[[records]]
name = "h1"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 2 }
[[records]]
name = "h2"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 3 }
"""

# Loaded by each worker before any task: a worker that reads a config, a record or a bundle from a
# path fails the task (and so the test) with this message.
PRELOAD = '''
def dask_setup(worker):
    import gpnarx.storage.bundle as bundle
    import gpnarx.training.config as config
    import gpnarx.storage.record_files as records

    def refuse(*args, **kwargs):
        raise RuntimeError(f"a Dask worker read from a path: {args[:1]}")

    config.load_config = refuse
    records.read_record = refuse
    bundle.load_bundle = refuse
'''

TIMING_KEYS = ("seconds", "wall_seconds", "fit_seconds")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask_cli() -> list[str]:
    exe = Path(sys.executable).with_name("dask")
    return [str(exe)] if exe.exists() else [shutil.which("dask") or "dask"]


def _env() -> dict:
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg")
    return env


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A scheduler and two single-thread workers on loopback; yields the scheduler address."""
    home = tmp_path_factory.mktemp("dask-cluster")
    preload = home / "refuse_paths.py"
    preload.write_text(PRELOAD)
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs, logs = [], []

    def start(args, name):
        log = open(home / f"{name}.log", "w")
        logs.append(log)
        procs.append(subprocess.Popen(_dask_cli() + args, cwd=home, env=_env(), stdout=log, stderr=subprocess.STDOUT))

    try:
        start(["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], "scheduler")
        for k in range(2):
            start(["worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard", "--host", "127.0.0.1",
                   "--name", f"w{k}", "--memory-limit", "0", "--preload", str(preload)], f"worker{k}")
        from distributed import Client

        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=90)
            assert sum(client.nthreads().values()) == 2
            from gpnarx.storage.record_files import read_record

            with pytest.raises(RuntimeError, match="read from a path"):  # the preload is in force
                client.submit(read_record, str(preload), pure=False).result(timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        for log in logs:
            log.close()


def _tasks_done(address) -> dict:
    """{task name: tasks finished so far} as the scheduler counts them (key prefix = the function's name)."""
    from distributed import Client

    with Client(address, timeout="30s") as client:
        return client.run_on_scheduler(
            lambda dask_scheduler: {k: v.state_counts["memory"] for k, v in dask_scheduler.task_prefixes.items()})


def _new_tasks(before: dict, after: dict) -> dict:
    return {k: n - before.get(k, 0) for k, n in after.items()
            if k in ("lag_cell_data", "evaluate_record", "render_record", "predict_record") and n > before.get(k, 0)}


def _gpnarx(args, cwd) -> tuple[int, dict | None, str, float]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gpnarx", "--json", *map(str, args)], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=300)
    wall = time.perf_counter() - t0
    out = json.loads(proc.stdout) if proc.stdout.strip() else None
    return proc.returncode, out, proc.stderr, wall


def _strip_timings(obj):
    if isinstance(obj, dict):
        return {k: _strip_timings(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [_strip_timings(v) for v in obj]
    return obj


def _assert_same(a, b, where="", rel=1e-9):
    """Same structure; numbers equal to ``rel`` (in practice they are bit-identical)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(set(a) ^ set(b))}"
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}", rel)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{where}: lengths differ"
        if a and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in a + b):
            np.testing.assert_allclose(a, b, rtol=rel, atol=0, err_msg=where)
        else:
            for k, (x, y) in enumerate(zip(a, b)):
                _assert_same(x, y, f"{where}[{k}]", rel)
    elif isinstance(a, float) and isinstance(b, float):
        assert math.isclose(a, b, rel_tol=rel, abs_tol=0) or (math.isnan(a) and math.isnan(b)), f"{where}: {a} != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.fixture(scope="module")
def trained(cluster, tmp_path_factory):
    """The same config trained with --choose-lags locally and on the cluster (each with its own lag cache)."""
    runs = {}
    for where in ("local", "dask"):
        d = tmp_path_factory.mktemp(f"train-{where}")
        cfg = d / "bw-dask.toml"
        cfg.write_text(CONFIG)
        args = ["train", cfg, "--registry", d / "registry", "--choose-lags", "--jobs", "1"]
        if where == "dask":
            args += ["--scheduler", cluster]
        before = _tasks_done(cluster)
        rc, out, err, wall = _gpnarx(args, cwd=d)
        assert rc == 0, err[-3000:]
        runs[where] = {"out": out, "wall": wall, "registry": d / "registry",
                       "tasks": _new_tasks(before, _tasks_done(cluster))}
    print(f"\ngpnarx train --choose-lags: local {runs['local']['wall']:.1f} s, "
          f"Dask (2 workers x 1 thread) {runs['dask']['wall']:.1f} s")
    return runs


def test_train_on_cluster_writes_the_same_bundle_metrics(trained):
    loc, dsk = trained["local"]["out"], trained["dask"]["out"]
    # the cluster did the work: 4 lag cells, 4 distinct free runs (lag-sweep has two roles), 5 report figures
    assert trained["dask"]["tasks"] == {"lag_cell_data": 4, "evaluate_record": 4, "render_record": 5}
    assert trained["local"]["tasks"] == {}
    assert loc["lags"]["cells"] == dsk["lags"]["cells"] == 4 and loc["lags"]["cached_cells"] == 0
    m_loc = json.loads((Path(loc["path"]) / "manifest.json").read_text())
    m_dsk = json.loads((Path(dsk["path"]) / "manifest.json").read_text())
    assert m_loc["lags"] == m_dsk["lags"] == {"ny": loc["lags"]["ny"], "nu": loc["lags"]["nu"]}
    assert set(m_loc["training"]["records"]) == {"lag-sweep", "sine", "h1", "h2"}
    assert m_loc["training"]["records"]["sine"]["fit"] > 50  # a model worth comparing
    _assert_same(_strip_timings(m_loc["training"]), _strip_timings(m_dsk["training"]), "training")
    _assert_same(m_loc["novelty"], m_dsk["novelty"], "novelty")
    for key in ("kernel", "hyperparameters", "noise_var", "nlml"):  # ML-II ran on the client both times
        _assert_same(m_loc[key], m_dsk[key], key)
    # the report, whose figures were drawn on the workers, is complete
    rep = Path(dsk["path"]) / "report"
    names = {r["name"] for r in json.loads((rep / "report.json").read_text())["records"]}
    assert names == {"lag-sweep", "sine", "h1", "h2"}
    pngs = sorted(p.name for p in rep.glob("record_*.png"))
    assert len(pngs) == 5 and all((rep / p).stat().st_size > 10_000 for p in pngs)  # lag-sweep twice (two roles)
    assert (rep / "lag_surface.png").is_file() and (rep / "report.html").stat().st_size > 100_000


def test_predict_many_on_cluster_matches_local_and_predict(trained, cluster, tmp_path, capsys):
    reg = trained["local"]["registry"]
    recs = []
    for k, (exc, amp) in enumerate([("sweep", 25), ("sweep", 40), ("sine", 30), ("multisine", 10)]):
        rec = tmp_path / "records" / f"r{k}-{exc}.npz"
        rec.parent.mkdir(exist_ok=True)
        extra = ["--freq", "30", "--duration", "0.5"] if exc == "sine" else ["--duration", "0.6"]
        if exc == "sweep":
            extra += ["--f0", "20", "--f1", "60"]
        assert main(["simulate", "bouc-wen", "--excitation", exc, "--amplitude", str(amp), *extra,
                     "--out", str(rec)]) == 0
        recs.append(rec)
    bad = tmp_path / "records" / "broken.csv"
    bad.write_text("this is not a record\n")
    capsys.readouterr()
    order = [recs[0], bad, *recs[1:]]
    runs = {}
    for where in ("local", "dask"):
        out_dir = tmp_path / f"out-{where}"
        args = ["predict-many", *order, "--registry", reg, "--model", "bw-dask", "--mc", "48", "--seed", "7",
                "--out", out_dir]
        if where == "dask":
            args += ["--scheduler", cluster]
        before = _tasks_done(cluster)
        rc, summary, err, wall = _gpnarx(args, cwd=tmp_path)
        assert _new_tasks(before, _tasks_done(cluster)) == ({"predict_record": 4} if where == "dask" else {})
        assert rc == 1, err[-3000:]  # one record failed ...
        assert summary["ok"] == 4 and summary["failed"] == 1 and summary["records"] == 5, summary
        assert "broken.csv" in err and len([ln for ln in err.splitlines() if "broken.csv" in ln]) == 1
        index = json.loads((out_dir / "index.json").read_text())
        status = {Path(e["record"]).name: e for e in index["records"]}
        assert status["broken.csv"]["status"] == "failed" and "u" in status["broken.csv"]["error"]
        assert [e["status"] for e in index["records"]] == ["ok", "failed", "ok", "ok", "ok"]  # ... the others kept
        runs[where] = {"dir": out_dir, "index": index, "wall": wall}
    assert runs["dask"]["index"]["where"].startswith("Dask tcp://127.0.0.1:")
    assert runs["local"]["index"]["where"] == "local"
    with capsys.disabled():
        print(f"\ngpnarx predict-many (4 records + 1 broken, 48 paths): local {runs['local']['wall']:.1f} s, "
              f"Dask (2 workers x 1 thread) {runs['dask']['wall']:.1f} s")
    for rec in recs:
        a = json.loads((runs["local"]["dir"] / f"{rec.stem}.json").read_text())
        b = json.loads((runs["dask"]["dir"] / f"{rec.stem}.json").read_text())
        assert len(a["mean"]) == a["n"] > 300 and a["mc_paths"] == 48 and a["fit"] > 0
        _assert_same(_strip_timings(a), _strip_timings(b), rec.stem)
    # one record's file is what 'gpnarx predict --json' answers for it
    assert main(["predict", "--registry", str(reg), "--model", "bw-dask", str(recs[2]), "--mc", "48", "--seed", "7",
                 "--json"]) == 0
    single = json.loads(capsys.readouterr().out)
    many = json.loads((runs["dask"]["dir"] / f"{recs[2].stem}.json").read_text())
    assert set(single) == set(many)
    _assert_same(_strip_timings(single), _strip_timings(many), "predict vs predict-many")
    # local cores (joblib) and an fsspec URL for --out: the same files
    url = (tmp_path / "out-jobs").as_uri()
    assert main(["predict-many", *map(str, recs), "--registry", str(reg), "--model", "bw-dask", "--mc", "48", "--seed",
                 "7", "--out", url, "--jobs", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["where"] == "local (2 jobs)"
    for rec in recs:
        _assert_same(_strip_timings(json.loads((tmp_path / "out-jobs" / f"{rec.stem}.json").read_text())),
                     _strip_timings(json.loads((runs["local"]["dir"] / f"{rec.stem}.json").read_text())), rec.stem)
    # a different seed gives different paths: the comparison above can fail
    assert main(["predict", "--registry", str(reg), "--model", "bw-dask", str(recs[2]), "--mc", "48", "--seed", "8",
                 "--json"]) == 0
    other = json.loads(capsys.readouterr().out)
    assert other["upper"] != many["upper"]


@pytest.mark.parametrize("extra, needle", [
    (["--scheduler", " "], "--scheduler"),
    (["--jobs", "0"], "--jobs"),
    (["--mc", "0"], "--mc"),
    (["--confidence", "1.5"], "--confidence"),
])
def test_predict_many_bad_options_are_one_line_exit_2(extra, needle, tmp_path, capsys):
    rc = main(["predict-many", str(tmp_path / "r.npz"), "--registry", str(tmp_path), "--model", "m",
               "--out", str(tmp_path / "out"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and needle in err, err
