"""Peak memory of a 1024-path Monte Carlo free-run: exact N=2000, sparse M=256, sklearn loop.

Each case runs in its own Python process (so allocations do not mix). Inside it the model is
built first, then ``tracemalloc`` (numpy reports its array buffers to it) is reset and a short
free-run is run; reported:
  * run peak: tracemalloc peak during the free-run, minus what was allocated before it (the
    working memory of the per-step products, temporaries and outputs);
  * held: arrays alive before the run (training data, model arrays, posterior factors);
  * maxrss: the process's resident-set high-water mark (``resource.getrusage``), all phases
    included (the sparse posterior's build over all 4064 rows, sklearn's fit, imports).
Product: ``model.freerun.simulate_mc`` with our exact / sparse posteriors. Baseline: the per-step
loop around ``GaussianProcessRegressor.predict(X, return_std=True)`` at the same N, kernel and
hyperparameters. Memory per step does not depend on the record length (outputs are O(length)).
``ratio=`` (equal work: same N, paths, float64, BLAS threads) = baseline (run peak + held) / ours
exact (run peak + held). ``user_ratio_sparse=`` = the same baseline / ours sparse M=256: NOT equal
work (a different model size), labelled by ``user_baseline=``.

    python bench/bench_memory.py [--quick] [--threads T]

``--pipeline``: the peak memory of whole ``gpnarx`` processes, what a pod's memory limit sees (one RESULT line):
  * train: ``python -m gpnarx train CONFIG --registry TMP`` (default: the shipped ``bert-real``: exact, its held-out
    noise and band calibrations, the report; ``--config`` another shipped config or a TOML file; ``--quick``: a small
    simulated exact config with a held-out noise calibration over 45 k rows, ``QUICK_CONFIG``);
  * predict: ``gpnarx predict`` of a record on the bundle just trained, the model's default method (bert-real:
    linearised; the 64 s 0.10 V sweep, ``PREDICT_RECORD``);
  * mc: ``gpnarx predict --method mc --mc 1024`` of the first 16 s of that record;
  * build_defaults (``--defaults``, minutes): ``gpnarx build-defaults`` into an empty registry (with the lab
    records, bert-real and its monitor too; ``defaults_built=`` names the bundles it wrote).
Each figure is the child's high-water mark (``ru_maxrss`` of ``wait4``: the process and the children it waited
for, each counted alone) and ``..._tree_pss_mib``, the largest sum of the proportional set sizes of the process
and its descendants seen at 0.1 s samples (forked workers: a shared page counted once, as a cgroup charges it).
Baseline, same run: train again with the held-out noise calibration's one-step predictions (eqs. 8-9) in one
call over every row (``model.estimator.ROW_BLOCK_FLOATS`` unbounded, the code before its row blocks: kept only
here, set in the baseline's process); ``ratio`` = baseline / product peak RSS of train. ``bundle_max_rel_diff``:
the two bundles' arrays and hyperparameters, max |a - b| / max |b| over each (0: byte-equal numbers).
``limit_mib`` (2048: deploy/k8s's replica limit) and ``within_limit`` (1 when every product figure is below it).

    python bench/bench_memory.py --pipeline [--quick] [--config NAME|TOML] [--defaults] [--bert-data DIR]
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import _common as C

MB = 1024.0 ** 2


def child(case: str, n: int, m: int, paths: int, steps: int) -> dict:
    import resource
    import tracemalloc
    import warnings

    import numpy as np
    from sklearn.gaussian_process import GaussianProcessRegressor  # noqa: F401  (import before tracing)

    from gpnarx.model.freerun import simulate_mc
    from gpnarx.model.gp import SparsePosterior, choose_inducing

    theta = C.THETA_REF
    r50 = C.protocol()[2]
    u = r50.u[900: 900 + C.NY + steps]
    y0 = r50.y[900: 900 + C.NY]
    C.training_set(n)  # simulate the records (cached) before tracing
    tracemalloc.start()
    X, y, xsc, ysc = C.training_set(n)
    if case == "exact":
        post = C.exact_posterior(theta, X, y)
    elif case == "sparse":
        Xa, ya, xsc, ysc = C.training_set(C.n_rows())
        k = C.make_kernel("matern32+cubic")
        k.set_theta(theta[:-1])
        post = SparsePosterior.fit(k, float(np.exp(theta[-1])), Xa, ya, choose_inducing(Xa, m, 0))
        del Xa, ya, X, y
    else:
        gpr = C.sk_gpr(theta, X, y)
    import gc

    gc.collect()
    held = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    if case in ("exact", "sparse"):
        simulate_mc(post, xsc, ysc, C.NY, C.NU, u, n_paths=paths, seed=0, y0=y0,
                    local=False)  # equal work with the scikit-learn loop: eq. 8-9 at every path
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            C.sklearn_freerun(gpr, float(np.exp(theta[-1])), xsc, ysc, u, y0, paths)
    secs = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux -> MB
    return {"case": case, "held_mb": held / MB, "run_peak_mb": (peak - held) / MB, "maxrss_mb": rss,
            "seconds": secs}


def main():
    def extra(ap):
        ap.add_argument("--child", default=None, help=argparse_hidden())
        ap.add_argument("--pipeline", action="store_true",
                        help="peak memory of whole gpnarx processes: train, predict, Monte Carlo predict")
        ap.add_argument("--config", default=None, help="--pipeline: the config trained (default: bert-real)")
        ap.add_argument("--defaults", action="store_true", help="--pipeline: gpnarx build-defaults too (minutes)")
        ap.add_argument("--bert-data", default=None, help="--pipeline: the lab records (GPNARX_BERT_DATA)")

    args = C.parse_args(__doc__, extra)
    if args.pipeline:
        pipeline(args)
        return
    q = args.quick
    n = 500 if q else 2000
    m = 64 if q else 256
    paths = 256 if q else 1024
    steps = 2 if q else 3
    if args.child:
        print(json.dumps(child(args.child, n, m, paths, steps)))
        return
    here = Path(__file__).resolve()
    res = {}
    for case in ("exact", "sparse", "sklearn"):
        cmd = [sys.executable, str(here), "--child", case] + (["--quick"] if q else [])
        if args.threads is not None:
            cmd += ["--threads", str(args.threads)]
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=str(here.parents[1]),
                             env={**os.environ, "PYTHONWARNINGS": "ignore"})
        if out.returncode != 0:
            sys.stderr.write(out.stderr)
            raise SystemExit(f"child {case} failed")
        res[case] = json.loads(out.stdout.strip().splitlines()[-1])
    tot = {k: v["held_mb"] + v["run_peak_mb"] for k, v in res.items()}
    print(f"bench_memory: {paths}-path free-run, {steps} steps, D={C.D}; exact N={n}, sparse M={m} "
          f"(posterior over all {C.n_rows()} rows), sklearn N={n}; {C.env_note()}")
    print(f"  {'case':<10} {'held MB':>8} {'run peak MB':>11} {'held+peak MB':>12} {'maxrss MB':>9}")
    for k, v in res.items():
        print(f"  {k:<10} {v['held_mb']:8.1f} {v['run_peak_mb']:11.1f} {tot[k]:12.1f} {v['maxrss_mb']:9.1f}")
    print("  (held = arrays alive before the run; run peak = extra tracemalloc peak during it; maxrss includes "
          "build and imports)")
    C.result(exact_mb=tot["exact"], sparse_mb=tot["sparse"], baseline=tot["sklearn"],
             baseline_what=f"sklearn-exact-N{n}-loop-same-paths", ratio=tot["sklearn"] / tot["exact"],
             user_baseline=f"sklearn-exact-N{n}-vs-sparse-M{m}", user_ratio_sparse=tot["sklearn"] / tot["sparse"],
             exact_run_peak_mb=res["exact"]["run_peak_mb"], baseline_run_peak_mb=res["sklearn"]["run_peak_mb"],
             exact_maxrss_mb=res["exact"]["maxrss_mb"], sparse_maxrss_mb=res["sparse"]["maxrss_mb"],
             baseline_maxrss_mb=res["sklearn"]["maxrss_mb"], N=n, M=m, paths=paths)


# --- --pipeline: whole gpnarx processes ------------------------------------------------------------------
MiB = 1024.0 ** 2
LIMIT_MIB = 2048  # deploy/k8s: a replica's memory limit
PREDICT_RECORD = "Chirp/Chirp0to40Hz/Chirp0p10"  # under the lab records: the 64 s 0.10 V sweep
MC_WINDOW = "0:16"  # s of PREDICT_RECORD for the Monte Carlo predict
QUICK_CONFIG = """\
name = "memory-quick"
description = "bench_memory --pipeline --quick: a small exact GP-NARX, its noise calibrated on 45 k held-out rows"
[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"
[physics]
mass = 2.0
[model]
ny = 4
nu = 4
mode = "exact"
max_train_points = 400
restarts = 0
noise_calibration = "lags"
[predict]
method = "linear"
mc_paths = 64
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 2.0, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 1 }
[[records]]
name = "lags-sweep"
roles = ["lags"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 60.0, f0 = 5.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 2 }
"""
# the baseline's process: the held-out calibration's predictions in one call over every row (before the row blocks)
UNBLOCKED = ("import sys\n"
             "import gpnarx.model.estimator as e\n"
             "e.ROW_BLOCK_FLOATS = 1 << 62\n"
             "from gpnarx.cli.main import main\n"
             "raise SystemExit(main(sys.argv[1:]))\n")


def _tree_pss_kib(pid: int) -> int:
    """Sum of Pss [KiB] of ``pid`` and its descendants (Linux /proc; 0 for a process gone meanwhile)."""
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1])
                    break
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return total


def _peak(cmd: list[str], env: dict, label: str) -> dict:
    """Run ``cmd``; its peak RSS [MiB] (wait4's ru_maxrss), its process tree's peak Pss [MiB] and seconds."""
    import threading

    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=str(C.ROOT), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    peak = [0]
    done = threading.Event()

    def sample():
        while not done.wait(0.1):
            peak[0] = max(peak[0], _tree_pss_kib(proc.pid))

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out = proc.stdout.read()
    _, status, ru = os.wait4(proc.pid, 0)
    done.set()
    th.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    secs = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(out[-4000:])
        raise SystemExit(f"{label} failed (exit {proc.returncode}): {' '.join(cmd)}")
    print(f"  {label:<16} peak RSS {ru.ru_maxrss / 1024.0:8.1f} MiB, tree Pss {peak[0] / 1024.0:8.1f} MiB, "
          f"{secs:6.1f} s", flush=True)
    return {"rss": ru.ru_maxrss / 1024.0, "pss": peak[0] / 1024.0, "s": secs}


def _bundle_diff(a: Path, b: Path) -> float:
    """Largest max|x - y| / max|y| over the arrays and hyperparameters of two bundles (0: the same numbers)."""
    from gpnarx.storage.bundle import load_bundle

    ma, mb = load_bundle(a).model, load_bundle(b).model
    xa, xb = ma.fitted_arrays(), mb.fitted_arrays()
    if sorted(xa) != sorted(xb):
        return float("inf")
    xa["hyper"] = np.array(list(ma.fitted_description()["hyperparameters"].values()), dtype=float)
    xb["hyper"] = np.array(list(mb.fitted_description()["hyperparameters"].values()), dtype=float)
    worst = 0.0
    for k in xa:
        x, y = np.asarray(xa[k], dtype=float), np.asarray(xb[k], dtype=float)
        if x.shape != y.shape:
            return float("inf")
        scale = float(np.max(np.abs(y))) if y.size else 0.0
        diff = float(np.max(np.abs(x - y))) if y.size else 0.0
        worst = max(worst, diff / scale if scale > 0 else diff)
    return worst


def _only_version(registry: Path, name: str) -> Path:
    found = sorted((registry / name).iterdir())
    return [p for p in found if p.is_dir()][-1]


def pipeline(args) -> None:
    import tempfile

    from gpnarx.training.datapaths import bert_data_dir

    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    if args.bert_data:
        env["GPNARX_BERT_DATA"] = str(Path(args.bert_data).resolve())
        os.environ["GPNARX_BERT_DATA"] = env["GPNARX_BERT_DATA"]
    if args.threads is not None:
        env["GPNARX_BLAS_THREADS"] = str(args.threads)
    py = [sys.executable]
    res = {}
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        tmp = Path(tmp)
        if args.quick:
            config = tmp / "memory-quick.toml"
            config.write_text(QUICK_CONFIG)
            name = "memory-quick"
        else:
            config = args.config or "bert-real"
            name = Path(config).stem if str(config).endswith(".toml") else str(config)
        print(f"bench_memory --pipeline: train {config}; {C.env_note()}, cores {os.cpu_count()}", flush=True)
        load0 = C.load()
        res["train"] = _peak(py + ["-m", "gpnarx", "train", str(config), "--registry", str(tmp / "product")], env,
                             "train")
        res["baseline"] = _peak(py + ["-c", UNBLOCKED, "train", str(config), "--registry", str(tmp / "baseline")],
                                env, "train baseline")
        product, baseline = _only_version(tmp / "product", name), _only_version(tmp / "baseline", name)
        diff = _bundle_diff(product, baseline)
        if args.quick:
            from gpnarx.storage.record_files import write_record
            from gpnarx.training.config import load_config

            record = write_record(tmp / "record.npz", load_config(config).records_for("lags")[0])
            predict, mc = [str(record)], [str(record), "--window", "0:4", "--mc", "64"]
            record_what = "the quick config's 60 s lags record; mc: its first 4 s"
        else:
            record = bert_data_dir() / PREDICT_RECORD
            if not record.is_dir():
                raise SystemExit(f"the lab records are not in {bert_data_dir()} (--bert-data DIR): {PREDICT_RECORD} "
                                 f"is the record predicted")
            predict, mc = [str(record)], [str(record), "--window", MC_WINDOW, "--mc", "1024"]
            record_what = f"{PREDICT_RECORD}; mc: its first 16 s"
        common = ["--registry", str(tmp / "product"), "--model", name, "--out", str(tmp / "out.npz")]
        res["predict"] = _peak(py + ["-m", "gpnarx", "predict"] + predict + common, env, "predict")
        res["mc"] = _peak(py + ["-m", "gpnarx", "predict", "--method", "mc"] + mc + common, env, "predict mc")
        if args.defaults:
            res["defaults"] = _peak(py + ["-m", "gpnarx", "build-defaults", "--registry", str(tmp / "defaults")],
                                    env, "build-defaults")
            built = sorted(d.name for d in (tmp / "defaults").iterdir() if d.is_dir() and any(
                v.is_dir() and (v / "manifest.json").is_file() for v in d.iterdir()))
    figures = ["train", "predict", "mc"] + (["defaults"] if args.defaults else [])
    worst = max(max(res[k]["rss"], res[k]["pss"]) for k in figures)
    extra = {}
    if args.defaults:
        extra = {"build_defaults_peak_mib": res["defaults"]["rss"],
                 "build_defaults_tree_pss_mib": res["defaults"]["pss"], "build_defaults_s": res["defaults"]["s"],
                 "defaults_built": ",".join(built), "bert_data": int((bert_data_dir() / "Sine").is_dir())}
    C.result(train_peak_mib=res["train"]["rss"], baseline=res["baseline"]["rss"],
             baseline_what="train-with-heldout-calibration-predict-in-one-call-same-config",
             ratio=res["baseline"]["rss"] / res["train"]["rss"], config=name,
             train_tree_pss_mib=res["train"]["pss"], baseline_tree_pss_mib=res["baseline"]["pss"],
             train_s=res["train"]["s"], baseline_s=res["baseline"]["s"], bundle_max_rel_diff=diff,
             predict_peak_mib=res["predict"]["rss"], predict_tree_pss_mib=res["predict"]["pss"],
             mc_peak_mib=res["mc"]["rss"], mc_tree_pss_mib=res["mc"]["pss"], mc_paths=1024 if not args.quick else 64,
             **extra, limit_mib=LIMIT_MIB, within_limit=int(worst < LIMIT_MIB),
             record=record_what.replace(" ", "_"), cores=os.cpu_count(), load=load0, load_end=C.load())


def argparse_hidden():
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
