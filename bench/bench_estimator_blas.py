"""The Python API's free run with its own BLAS limit: ``GPNARX.simulate`` as a user's script calls it.

Product: ``model.simulate(u, n_paths=P, seed=0)`` on a trained Bouc-Wen model, in this process, whose BLAS
nobody set (library defaults: OpenBLAS uses every core); the estimator limits BLAS to
``GPNARX_BLAS_THREADS`` (default 1) around its free run (``gpnarx.runtime.free_run_blas``, the CLI's tuning)
and restores the caller's threads after.

Baseline, equal work (``ratio=``): the same call on the same model, record, paths and seed with
``GPNARX_BLAS_THREADS=0`` (the estimator leaves BLAS as it is: the library's default threads), which is what
``GPNARX.simulate`` did before it limited BLAS itself. Calls alternate (A, B, A, B, ...); ratio = median over
repetitions of baseline wall / product wall. ``max_mean_diff``: the two means' largest difference (thread
counts only change summation order).

Model: the bundle trained from the shipped ``configs/bouc-wen.toml`` (sparse, M=256), cached as
``bench_predict_e2e.py`` caches it (trained on first use, ``--retrain`` to redo); ``--quick``: a tiny GP-NARX
fitted here. Record: the first ``--seconds`` of the 50 N Bouc-Wen sweep (750 Hz).

    python bench/bench_estimator_blas.py [--quick] [--seconds S] [--paths P] [--reps R] [--retrain]
"""
from __future__ import annotations

import os
import time
import warnings

import numpy as np

import _common as C

ENV = "GPNARX_BLAS_THREADS"


def extra(ap):
    ap.add_argument("--seconds", type=float, default=None, help="record length [s] (default 2; --quick 1)")
    ap.add_argument("--paths", type=int, default=None, help="Monte Carlo paths (default 256; --quick 64)")
    ap.add_argument("--reps", type=int, default=None, help="repetitions of each side (default 3; --quick 2)")
    ap.add_argument("--retrain", action="store_true", help="retrain the cached bundle")


def model_for(args):
    if args.quick:
        from gpnarx.model.estimator import GPNARX

        pairs, _, _ = C.protocol()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=32, max_train_points=150, n_restarts=0)
            m.fit(pairs)
        return m, "tiny", "tiny sparse GP-NARX fitted here (M=32, 150 ML-II rows)"
    from bench_predict_e2e import cached_registry

    from gpnarx.storage.registry import Registry

    reg, note = cached_registry(False, args.retrain)
    bundle = Registry(reg).scan().get("bouc-wen")
    return bundle.model, "bouc-wen", f"bouc-wen from configs/bouc-wen.toml ({note})"


def timed(model, u, paths, env_value):
    if env_value is None:
        os.environ.pop(ENV, None)
    else:
        os.environ[ENV] = env_value
    t0 = time.perf_counter()
    run = model.simulate(u, n_paths=paths, seed=0)
    return time.perf_counter() - t0, run


def main():
    args = C.parse_args(__doc__, extra)
    seconds = args.seconds or (1.0 if args.quick else 2.0)
    paths = args.paths or (64 if args.quick else 256)
    reps = args.reps or (2 if args.quick else 3)
    os.environ.pop(ENV, None)
    model, label, what = model_for(args)
    u = C.record(50.0).u[: int(round(seconds * 750.0))]
    library_threads = C.blas_threads()  # what BLAS has in this process when nobody sets it
    timed(model, u[:200], 8, None)  # warm-up (first-call imports and allocations)
    product, baseline, means = [], [], {}
    for _ in range(reps):  # interleaved: load from other processes hits both sides
        t, run = timed(model, u, paths, None)
        product.append(t)
        means["product"] = run.mean
        t, run = timed(model, u, paths, "0")
        baseline.append(t)
        means["baseline"] = run.mean
    os.environ.pop(ENV, None)
    assert C.blas_threads() == library_threads, "the caller's BLAS threads were not restored"
    C.result(bench="estimator_blas", model=label, samples=u.size, paths=paths,
             reps=reps, blas_library_threads=library_threads, product_s=C.median(product),
             baseline=C.median(baseline), baseline_what="GPNARX.simulate_with_BLAS_unlimited(GPNARX_BLAS_THREADS=0)",
             ratio=C.median_ratio(baseline, product),
             max_mean_diff=float(np.max(np.abs(means["product"] - means["baseline"]))),
             load=C.load())
    print(f"# {what}; record {u.size} samples ({u.size / 750.0:g} s at 750 Hz), {paths} paths; "
          f"product {C.fmt(C.median(product))} s with 1 BLAS thread, baseline {C.fmt(C.median(baseline))} s with "
          f"{library_threads} (library default)")


if __name__ == "__main__":
    main()
