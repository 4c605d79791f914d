"""End to end: ``gpnarx predict --mc 1024`` on a 2031-sample Bouc-Wen sweep, timed as a process.

Product: a bundle trained from the shipped ``configs/bouc-wen.toml`` (sparse mode, M=256 inducing
points over all ~4000 training rows, ML-II on 1000 stride rows; trained once with
``gpnarx train ... --mc 16 --no-report`` into a cached registry, ``--retrain`` to redo it), and the
50 N Bouc-Wen sweep (5-150 Hz at 53.55 Hz/s: 2031 samples at 750 Hz, written by
``gpnarx simulate``). Timed: the whole ``python -m gpnarx predict --registry R --model
bouc-wen REC --mc 1024 --out OUT.npz --json`` subprocess (interpreter start, imports, bundle load
with checksums, 1024-path Monte Carlo free run from rest, writing OUT.npz and the JSON);
path-steps = 2031 x 1024. The command applies its process tuning (``gpnarx/runtime.py``: one BLAS
thread, glibc mmap threshold 32 MiB).

Baseline, equal work (``ratio=``): a subprocess of this script (``--reference-child``) that does
the same job with the same process tuning (it calls the same ``tune_for_free_run``): it loads the
same bundle through the same registry code, reads the record, runs the 1024-path Monte Carlo
free run from rest over the whole record with ``_common.NumpySparse`` (a plain numpy/scipy
evaluation of the bundle's own sparse posterior: same M, Z, w, G, float64; scikit-learn has no
sparse GP), computes fit and coverage and writes OUT.npz and a JSON line. Product and baseline
processes alternate (A, B, A, B, ...); ratio = median over repetitions of baseline wall / product
wall. Also timed once: the product command with its tuning off (``GPNARX_BLAS_THREADS=0
GPNARX_MMAP_THRESHOLD=0``: library-default BLAS threads, default malloc), to show what the tuning buys.

User comparison (NOT equal work; ``user_ratio=``, ``user_baseline=``): the per-step loop a user
would write around scikit-learn's ``GaussianProcessRegressor.predict(X, return_std=True)``, exact GP
at N=4000 training rows of the Bouc-Wen protocol (D=37), 1024 paths, in this process with library
defaults (or ``--threads``); a few steps, half before and half after the product runs, converted to
path-steps per second. Its hyperparameters are THETA_REF (a per-step timing does not depend on
their values). user_ratio = product path-steps/s (whole process) / that.

    python bench/bench_predict_e2e.py [--quick] [--threads N] [--retrain] [--reps R]

--quick: a tiny config (M=32, 150 ML-II rows, train records only), 300 samples, 256 paths, N=500 user baseline.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C

CONFIG = C.ROOT / "configs" / "bouc-wen.toml"
QUICK_CONFIG = """# bench_predict_e2e --quick: a tiny Bouc-Wen model (not the shipped one)
name = "bouc-wen"
description = "tiny Bouc-Wen model for the bench smoke test"

[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"

[physics]
mass = 2.0
input_gain = 1.0

[model]
ny = 20
nu = 17
kernel = "matern32+cubic"
mode = "sparse"
inducing = 32
max_train_points = 150
selection = "stride"
restarts = 0
seed = 0

[predict]
mc_paths = 256
confidence = 0.99

[[records]]
name = "sweep-10N"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 10.0, f0 = 5.0, f1 = 150.0, rate = 53.0 }
noise = { fraction = 0.1, reference = "sweep-10N", seed = 101 }

[[records]]
name = "sweep-80N"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 80.0, f0 = 5.0, f1 = 150.0, rate = 53.0 }
noise = { fraction = 0.1, reference = "sweep-10N", seed = 102 }
"""


def cli(*argv, env=None, timeout=3600):
    """Run ``python -m gpnarx ARGV`` from the repository root; (seconds, CompletedProcess)."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(C.ROOT) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    e.pop("GPNARX_REGISTRY", None)
    if env:
        e.update(env)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gpnarx", *map(str, argv)], cwd=C.ROOT, env=e, check=False,
                          capture_output=True, text=True, timeout=timeout)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"gpnarx {argv[0]} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return dt, proc


def cached_registry(quick: bool, retrain: bool) -> tuple[Path, str]:
    """Registry holding a 'bouc-wen' bundle trained from the config; trained on first use only."""
    text = QUICK_CONFIG if quick else CONFIG.read_text()
    key = hashlib.sha256(text.encode()).hexdigest()[:12]
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "bench-e2e" / key
    reg = base / "registry"
    note = f"cached registry {reg}"
    if retrain and base.exists():
        import shutil

        shutil.rmtree(base)
    if not (reg / "bouc-wen").is_dir():
        base.mkdir(parents=True, exist_ok=True)
        cfg = base / "config.toml"
        cfg.write_text(text)
        t, _ = cli("train", cfg, "--registry", reg, "--mc", 16, "--no-report", "--json")
        note = f"trained into {reg} in {t:.0f} s (cached for later runs)"
    return reg, note


def reference_child(registry: str, record: str, out: str, paths: int) -> None:
    """The equal-work baseline process: same tuning, same bundle, numpy evaluation of its sparse posterior."""
    from gpnarx.model.metrics import summary
    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.registry import Registry

    t0 = time.perf_counter()
    tuning = tune_for_free_run(None)
    model = Registry(registry).scan().get("bouc-wen").model
    d = np.load(record)
    u, y = np.asarray(d["u"], float), np.asarray(d["y"], float)
    ref = C.NumpySparse(model.posterior_)
    ny = model.ny
    uu = np.concatenate([np.zeros(ny), u])  # from rest: ny zero outputs and inputs before the record
    mean, lower, upper, sim_s, path_steps, _ = C.mc_freerun(
        ref.predict, float(model.posterior_.noise_var), model.x_scaler_, model.y_scaler_, uu, np.zeros(ny), paths,
        seed=0, ny=ny, nu=model.nu)
    mean, lower, upper = mean[ny:], lower[ny:], upper[ny:]
    m = summary(y, mean, lower, upper)
    np.savez(out, fs=float(d["fs"]), u=u, y=y, mean=mean, lower=lower, upper=upper)
    print(json.dumps({"seconds": sim_s, "path_steps": path_steps, "fit": m["fit"], "coverage": m["coverage"],
                      "tuning": tuning, "process_s": time.perf_counter() - t0}))


def main():
    def extra(ap):
        ap.add_argument("--retrain", action="store_true", help="retrain the cached bundle")
        ap.add_argument("--reps", type=int, default=None, help="interleaved repetitions (default 3; 2 with --quick)")
        ap.add_argument("--reference-child", nargs=4, metavar=("REGISTRY", "RECORD", "OUT", "PATHS"),
                        help=argparse.SUPPRESS)

    args = C.parse_args(__doc__, extra)
    if args.reference_child:
        reg, rec, out, paths = args.reference_child
        reference_child(reg, rec, out, int(paths))
        return
    with tempfile.TemporaryDirectory(prefix="gpnarx-e2e-") as tmp:
        run(args, Path(tmp))


def child(*argv, timeout=3600):
    """Run this script as the equal-work baseline process; (seconds, parsed JSON line)."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(C.ROOT) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--reference-child", *map(str, argv)],
                          cwd=C.ROOT, env=e, check=False, capture_output=True, text=True, timeout=timeout)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"reference child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return dt, json.loads(proc.stdout.strip().splitlines()[-1])


def run(args, tmp: Path):
    q = args.quick
    P = 256 if q else 1024
    N_user = 500 if q else 4000
    user_steps = 2 if q else 4
    reps = args.reps or (2 if q else 3)

    reg, reg_note = cached_registry(q, args.retrain)
    rec = tmp / "sweep50.npz"
    cli("simulate", "bouc-wen", "--excitation", "sweep", "--amplitude", 50, "--rate", 53.55, "--out", rec)
    if q:
        d = dict(np.load(rec))
        np.savez(rec, u=d["u"][:300], y=d["y"][:300], fs=d["fs"])
    n = int(np.load(rec)["u"].size)
    out = tmp / "pred.npz"
    out_ref = tmp / "ref.npz"
    predict = ("predict", "--registry", reg, "--model", "bouc-wen", rec, "--mc", P, "--out", out, "--json")

    # the equal-work reference computes the bundle's own posterior: check it on one regressor block
    from gpnarx.storage.registry import Registry

    model = Registry(reg).scan().get("bouc-wen").model
    Zp = model.posterior_.points
    Xchk = Zp + 0.05 * np.random.default_rng(0).standard_normal(Zp.shape)
    ref_mean_diff = float(np.max(np.abs(model.posterior_.predict(Xchk)[0] - C.NumpySparse(model.posterior_)
                                        .predict(Xchk)[0])))
    del model

    # user comparison set-up (in this process) and its first half
    theta = C.THETA_REF.copy()
    Xb, yb, xsc, ysc = C.training_set(N_user)
    gpr = C.sk_gpr(theta, Xb, yb)
    noise = float(np.exp(theta[-1]))
    r50 = C.record(50.0)
    uu = np.concatenate([np.zeros(C.NY), r50.u])
    y0 = np.zeros(C.NY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + 1], y0, P)  # warm-up
        *_, s1, ps1, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + user_steps // 2], y0, P, seed=1)

    cli(*predict)  # warm-up (file cache, .pyc)
    last = {}

    def product():
        t, proc = cli(*predict)
        last["product"] = json.loads(proc.stdout)
        return t

    def baseline():
        t, res = child(reg, rec, out_ref, P)
        last["baseline"] = res
        return t

    walls = C.interleave({"product": product, "baseline": baseline}, reps)
    res, bres = last["product"], last["baseline"]
    untuned, _ = cli(*predict, env={"GPNARX_BLAS_THREADS": "0", "GPNARX_MMAP_THRESHOLD": "0"})

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        *_, s2, ps2, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + user_steps - user_steps // 2], y0, P,
                                           seed=2)
    user_ps = (ps1 + ps2) / (s1 + s2)
    user_step_s = P / user_ps
    path_steps = n * P
    wall = C.median(walls["product"])
    base_wall = C.median(walls["baseline"])
    ps = path_steps / wall
    base_ps = path_steps / base_wall
    ratio = C.median_ratio(walls["baseline"], walls["product"])
    sim_s = float(res["seconds"])
    assert out.is_file() and out_ref.is_file() and len(res["mean"]) == n

    print(f"bench_predict_e2e: gpnarx predict --mc {P} on a {n}-sample Bouc-Wen 50 N sweep ({reg_note}); "
          f"{C.env_note()} in the bench process")
    print(f"  product, whole process (start, load, predict, write): "
          f"{', '.join(f'{w:.2f}' for w in walls['product'])} s "
          f"(median {wall:.2f} s; simulate() itself {sim_s:.2f} s); {ps:,.0f} path-steps/s; "
          f"fit {res.get('fit', float('nan')):.1f} %, coverage {res.get('coverage', float('nan')):.1f} %")
    print(f"  baseline (equal work), numpy reference of the same bundle's posterior, same tuning {bres['tuning']}, "
          f"whole process: {', '.join(f'{w:.2f}' for w in walls['baseline'])} s (median {base_wall:.2f} s; its loop "
          f"{bres['seconds']:.2f} s); fit {bres['fit']:.1f} %, coverage {bres['coverage']:.1f} %; max |mean diff| on "
          f"one block {ref_mean_diff:.1e}")
    print(f"  ratio (median of {reps} interleaved baseline/product wall ratios): {ratio:.2f}")
    print(f"  same command with the process tuning off (library BLAS threads, default malloc): {untuned:.2f} s "
          f"(x{untuned / wall:.2f} the tuned median)")
    print(f"  user comparison (NOT equal work): sklearn predict loop, exact N={N_user}, D={C.D}, {P} paths, "
          f"in this process: {user_step_s:.3f} s/step measured on {(ps1 + ps2) // P} steps (half before, half "
          f"after); {user_ps:,.0f} path-steps/s; the record would take {user_step_s * n:.0f} s (extrapolated); "
          f"user_ratio {ps / user_ps:.1f}")
    C.result(path_steps_per_s=ps, baseline=base_ps, baseline_what="numpy-reference-same-bundle-same-tuning-process",
             ratio=ratio, wall_s=wall, baseline_wall_s=base_wall, wall_best_s=min(walls["product"]),
             simulate_s=sim_s, baseline_loop_s=float(bres["seconds"]), untuned_wall_s=untuned,
             user_baseline=f"sklearn-exact-N{N_user}-inprocess", user_baseline_ps=user_ps, user_ratio=ps / user_ps,
             ref_max_mean_diff=ref_mean_diff, reps=reps, samples=n, paths=P,
             fit=res.get("fit", float("nan")), coverage=res.get("coverage", float("nan")),
             baseline_fit=bres["fit"], baseline_coverage=bres["coverage"], load=C.load(),
             blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
