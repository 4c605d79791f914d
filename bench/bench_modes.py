"""Free-run throughput by mode: 1024 Monte Carlo paths on the Bouc-Wen 50 N sweep.

Product (``GPNARX(...).fit(records, theta=theta).simulate(u, ...)``, the shipped code path), same
hyperparameters (ML-II, one start, on a stride subset) for every mode:
  * exact, N=2000 training points (MC);
  * sparse, M=256 and M=512 inducing points (k-means) over all 4064 training rows (MC);
  * linearised (first-order propagation, one path) on the exact N=2000 model and on sparse M=512.
Exact MC costs ~0.1-0.5 s per step, so it runs a segment of the record (the first steps; stated in
the output) and its rate is path-steps per second over that segment; sparse MC runs the whole record.
Baseline: the per-step loop a user would write around scikit-learn's
``GaussianProcessRegressor.predict(X, return_std=True)`` at N=4000 (D=37), same kernel and
hyperparameters, 1024 paths. It runs only a few steps (half before, half after the product runs),
and its time for the whole record is extrapolated: steps x measured seconds per step.
linear_speedup = baseline's extrapolated MC time for the record / linearised wall time for it.

    python bench/bench_modes.py [--quick]
"""
from __future__ import annotations

import time
import warnings

import numpy as np

import _common as C
from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import coverage, fit_percent


def main():
    args = C.parse_args(__doc__)
    q = args.quick
    P = 256 if q else 1024
    N_exact = 500 if q else 2000
    N_base = 500 if q else 4000
    Ms = (32, 64) if q else (256, 512)
    exact_steps = 5 if q else 30
    base_steps = 2 if q else 6  # split half before, half after the product runs
    rec_len = 150 if q else None  # quick: first 150 samples of the 50 N sweep

    t0 = time.perf_counter()
    theta, _, hyp = C.hyperparameters(q)
    pairs, _, r50 = C.protocol()
    u50 = r50.u if rec_len is None else r50.u[:rec_len]
    y50 = r50.y if rec_len is None else r50.y[:rec_len]
    n = u50.size

    def model(mode, **kw):
        m = GPNARX(ny=C.NY, nu=C.NU, mode=mode, max_train_points=N_exact, n_restarts=0, **kw)
        t = time.perf_counter()
        m.fit(pairs, theta=theta)
        return m, time.perf_counter() - t

    # the baseline: sklearn at N_base with the same hyperparameters and standardisation
    Xb, yb, xsc, ysc = C.training_set(N_base)
    gpr = C.sk_gpr(theta, Xb, yb)
    noise = float(np.exp(theta[-1]))
    y0 = np.zeros(C.NY)  # from rest, like the product's simulate() without y0
    uu = np.concatenate([np.zeros(C.NY), u50])  # the baseline loop starts after ny known (zero) outputs
    C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + 1], y0, P)  # warm-up
    setup_s = time.perf_counter() - t0

    base_s = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        *_, s, ps, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + base_steps // 2], y0, P)
    base_s.append((s, ps))

    rows = {}
    exact, fit_exact = model("exact")
    exact.simulate(u50[:2], n_paths=P, seed=0)  # warm-up
    fr = exact.simulate(u50[:exact_steps], n_paths=P, seed=0)
    rows["exact"] = dict(N=N_exact, steps=exact_steps, seconds=fr.seconds, ps=fr.path_steps / fr.seconds,
                         fit=fit_exact, run=None)
    sparse = {}
    for M in Ms:
        m, fs_ = model("sparse", n_inducing=M)
        sparse[M] = m
        m.simulate(u50[:2], n_paths=P, seed=0)
        fr = m.simulate(u50, n_paths=P, seed=0)
        rows[f"sparse{M}"] = dict(N=M, steps=n, seconds=fr.seconds, ps=fr.path_steps / fr.seconds, fit=fs_, run=fr)
    lin = {}
    for name, m in (("linear (exact N=%d)" % N_exact, exact), ("linear (sparse M=%d)" % Ms[-1], sparse[Ms[-1]])):
        m.simulate(u50[:5], method="linear")
        fr = m.simulate(u50, method="linear")
        lin[name] = fr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        *_, s, ps, _ = C.sklearn_freerun(gpr, noise, xsc, ysc, uu[: C.NY + base_steps - base_steps // 2], y0, P)
    base_s.append((s, ps))
    base_sec_per_step = sum(s for s, _ in base_s) / (sum(ps for _, ps in base_s) / P)
    base_ps = P / base_sec_per_step
    base_record_s = n * base_sec_per_step  # extrapolated MC time for the whole record

    print(f"bench_modes: Bouc-Wen 50 N sweep ({n} samples), {P} paths, D={C.D}; hyperparameters: {hyp}; "
          f"setup {setup_s:.1f} s; {C.env_note()}")
    print(f"  baseline sklearn predict loop, N={N_base}: {base_sec_per_step:.3f} s/step measured on "
          f"{sum(ps for _, ps in base_s) // P} steps (half before, half after); extrapolated to the record: "
          f"{base_record_s:.0f} s; {base_ps:,.0f} path-steps/s")
    print(f"  {'mode':<24} {'N/M':>5} {'steps':>6} {'seconds':>8} {'path-steps/s':>13} {'x baseline':>10} "
          f"{'fit %':>6} {'cov99 %':>7} {'build s':>7}")
    for name, r in rows.items():
        fitp = cov = float("nan")
        if r["run"] is not None:
            fitp = fit_percent(y50, r["run"].mean)
            cov = coverage(y50, r["run"].lower, r["run"].upper)
        print(f"  {name + ' MC':<24} {r['N']:>5} {r['steps']:>6} {r['seconds']:8.2f} {r['ps']:13,.0f} "
              f"{r['ps'] / base_ps:10.1f} {fitp:6.1f} {cov:7.1f} {r['fit']:7.2f}")
    for name, fr in lin.items():
        print(f"  {name:<24} {'':>5} {n:>6} {fr.seconds:8.2f} {'':>13} {base_record_s / fr.seconds:10.1f} "
              f"{fit_percent(y50, fr.mean):6.1f} {coverage(y50, fr.lower, fr.upper):7.1f}")
    print("  (exact MC runs the first %d steps only; 'x baseline' for linear = baseline extrapolated MC time for "
          "the record / linear wall time; fit/coverage against the noise-free 50 N response)" % exact_steps)
    lin_exact = list(lin.values())[0]
    lin_sparse = list(lin.values())[1]
    C.result(exact=rows["exact"]["ps"], **{f"sparse{M}": rows[f"sparse{M}"]["ps"] for M in Ms},
             linear_speedup=base_record_s / lin_exact.seconds, linear_s=lin_exact.seconds,
             linear_sparse_speedup=base_record_s / lin_sparse.seconds,
             baseline=base_ps, baseline_record_s=base_record_s,
             ratio_sparse=rows[f"sparse{Ms[0]}"]["ps"] / base_ps,
             **{f"ratio_sparse{Ms[-1]}": rows[f"sparse{Ms[-1]}"]["ps"] / base_ps},
             ratio_exact=rows["exact"]["ps"] / base_ps, ratio=rows[f"sparse{Ms[0]}"]["ps"] / base_ps,
             paths=P, record=n, load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
