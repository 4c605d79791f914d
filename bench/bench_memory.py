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
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

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
    extra = lambda ap: ap.add_argument("--child", default=None, help=argparse_hidden())  # noqa: E731
    args = C.parse_args(__doc__, extra)
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


def argparse_hidden():
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
