"""End to end: ``gpnarx predict --mc 1024`` on a 2031-sample Bouc-Wen sweep, timed as a process.

Product: a bundle trained from the shipped ``configs/bouc-wen.toml`` (sparse mode, M=256 inducing
points over all ~4000 training rows, ML-II on 1000 stride rows; trained once with
``gpnarx train ... --mc 16 --no-report`` into a cached registry, ``--retrain`` to redo it), and the
50 N Bouc-Wen sweep (5-150 Hz at 53.55 Hz/s: 2031 samples at 750 Hz, written by
``gpnarx simulate``). Timed: the whole ``python -m gpnarx predict --registry R --model
bouc-wen REC --mc 1024 --out OUT.npz --json`` subprocess (interpreter start, imports, bundle load
with checksums, 1024-path Monte Carlo free run from rest, writing OUT.npz and the JSON), best and
median of a few runs; path-steps = 2031 x 1024. Also timed once more with the process tuning off
(``GPNARX_BLAS_THREADS=0 GPNARX_MMAP_THRESHOLD=0``: library-default BLAS threads, default malloc)
to show what ``model/runtime.py`` buys.

Baseline (same run): the per-step loop a user would write around scikit-learn's
``GaussianProcessRegressor.predict(X, return_std=True)``, exact GP at N=4000 training rows of the
Bouc-Wen protocol, D=37 (ny=20, nu=17), 1024 paths (``_common.sklearn_freerun``); it runs a few
steps (half before, half after the product) and is converted to path-steps per second.
Its hyperparameters are THETA_REF (a per-step timing does not depend on their values).
ratio = product path-steps/s (whole process) / baseline path-steps/s. Target >= 50.

    python bench/bench_predict_e2e.py [--quick] [--threads N] [--retrain]

--quick: a tiny config (M=32, 150 ML-II rows, train records only), 300 samples, 256 paths, N=500 baseline.
"""
from __future__ import annotations

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


def main():
    args = C.parse_args(__doc__, lambda ap: ap.add_argument("--retrain", action="store_true",
                                                            help="retrain the cached bundle"))
    with tempfile.TemporaryDirectory(prefix="gpnarx-e2e-") as tmp:
        run(args, Path(tmp))


def run(args, tmp: Path):
    q = args.quick
    P = 256 if q else 1024
    N_base = 500 if q else 4000
    base_steps = 2 if q else 4
    reps = 2 if q else 3

    reg, reg_note = cached_registry(q, args.retrain)
    rec = tmp / "sweep50.npz"
    cli("simulate", "bouc-wen", "--excitation", "sweep", "--amplitude", 50, "--rate", 53.55, "--out", rec)
    if q:
        d = dict(np.load(rec))
        np.savez(rec, u=d["u"][:300], y=d["y"][:300], fs=d["fs"])
    n = int(np.load(rec)["u"].size)
    out = tmp / "pred.npz"
    predict = ("predict", "--registry", reg, "--model", "bouc-wen", rec, "--mc", P, "--out", out, "--json")

    # baseline set-up (in this process) and its first half
    theta = C.THETA_REF.copy()
    Xb, yb, xsc, ysc = C.training_set(N_base)
    gpr = C.sk_gpr(theta, Xb, yb)
    noise = float(np.exp(theta[-1]))
    r50 = C.record(50.0)
    uu = np.concatenate([np.zeros(C.NY), r50.u])
    y0 = np.zeros(C.NY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + 1], y0, P)  # warm-up
        *_, s1, ps1, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + base_steps // 2], y0, P, seed=1)

    cli(*predict)  # warm-up (file cache, .pyc)
    walls = []
    for _ in range(reps):
        t, proc = cli(*predict)
        walls.append(t)
    res = json.loads(proc.stdout)
    untuned, _ = cli(*predict, env={"GPNARX_BLAS_THREADS": "0", "GPNARX_MMAP_THRESHOLD": "0"})

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        *_, s2, ps2, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + base_steps - base_steps // 2], y0, P,
                                           seed=2)
    base_ps = (ps1 + ps2) / (s1 + s2)
    base_step_s = P / base_ps
    path_steps = n * P
    wall = C.median(walls)
    ps = path_steps / wall
    ps_best = path_steps / min(walls)
    sim_s = float(res["seconds"])
    assert out.is_file() and len(res["mean"]) == n

    print(f"bench_predict_e2e: gpnarx predict --mc {P} on a {n}-sample Bouc-Wen 50 N sweep ({reg_note}); "
          f"{C.env_note()} in the bench process")
    print(f"  product, whole process (start, load, predict, write): {', '.join(f'{w:.2f}' for w in walls)} s "
          f"(median {wall:.2f} s; simulate() itself {sim_s:.2f} s); {ps:,.0f} path-steps/s "
          f"(best {ps_best:,.0f}); fit {res.get('fit', float('nan')):.1f} %, "
          f"coverage {res.get('coverage', float('nan')):.1f} %")
    print(f"  same command with the process tuning off (library BLAS threads, default malloc): {untuned:.2f} s "
          f"(x{untuned / wall:.2f} the tuned median)")
    print(f"  baseline sklearn predict loop, exact N={N_base}, D={C.D}, {P} paths: {base_step_s:.3f} s/step "
          f"measured on {(ps1 + ps2) // P} steps (half before, half after); {base_ps:,.0f} path-steps/s; "
          f"the record would take {base_step_s * n:.0f} s (extrapolated)")
    print(f"  ratio {ps / base_ps:.1f} (target >= 50)")
    C.result(path_steps_per_s=ps, baseline=base_ps, ratio=ps / base_ps, wall_s=wall, wall_best_s=min(walls),
             simulate_s=sim_s, untuned_wall_s=untuned, samples=n, paths=P, N_base=N_base,
             fit=res.get("fit", float("nan")), coverage=res.get("coverage", float("nan")), load=C.load(),
             blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
