"""ML-II fit time against N: ours vs scikit-learn's GaussianProcessRegressor.fit.

Product: ``model.gp.fit_ml2`` (eq. 13: analytic gradient from one Cholesky and one potri in a
reused workspace, L-BFGS-B over the log-hyperparameters of eq. 12 and the noise), one start
(n_restarts=0), data-scaled initial point, timed twice: "cold" (full-N L-BFGS-B from the data-scaled
point) and "default" (what ``GPNARX`` runs: from N=2000 the start is first optimised on N/4 strided
rows, ``warm_start_subset``, then full-N L-BFGS-B from there, with the redundant cubic scale s held
at its start value, ``hold_redundant``). The RESULT ratio is the default's.
Baseline: scikit-learn with the same kernel written as
``C*Matern(nu=1.5) + C*DotProduct**3 + WhiteKernel`` and its own optimiser (fmin_l_bfgs_b,
n_restarts_optimizer=0), started from the same initial hyperparameters, with bounds wide enough to
contain our optimum (sklearn's defaults would clip the cubic amplitude, about 1e-12 here).
Both fit the same standardised Bouc-Wen training rows (stride selection), back to back per N.
NLMLs are comparable: sklearn's WhiteKernel plays our noise variance (its default alpha=1e-10 adds
a negligible jitter); sklearn's optimum is also re-evaluated with our NLML as a cross-check.

    python bench/bench_fit.py [--quick] [--threads N] [--sizes 1000,2000,4000] [--restarts R]
"""
from __future__ import annotations

import math
import time
import warnings

import numpy as np
from scipy.optimize import minimize

import _common as C
from gpnarx.model.gp import default_warm_start_subset, fit_ml2, initial_theta, nlml_and_grad
from gpnarx.model.kernels import make_kernel

EVALS = {"sklearn": 0}


def sk_fit(theta0, X, y, max_iter=None):
    """sklearn fit; the optimiser callable is sklearn's default (L-BFGS-B, jac=True, bounds) plus a call count."""
    from sklearn.gaussian_process import GaussianProcessRegressor

    def optimizer(obj_func, initial_theta, bounds):
        def f(t):
            EVALS["sklearn"] += 1
            return obj_func(t)

        opts = {"maxiter": max_iter} if max_iter else None
        r = minimize(f, initial_theta, method="L-BFGS-B", jac=True, bounds=bounds, options=opts)
        return r.x, r.fun

    gpr = GaussianProcessRegressor(C.sk_kernel(theta0, fixed=False, white=True), optimizer=optimizer,
                                   n_restarts_optimizer=0, normalize_y=False, random_state=0)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gpr.fit(X, y)
    return gpr, time.perf_counter() - t0


def sk_theta_as_ours(gpr) -> np.ndarray:
    """sklearn's fitted parameters in our parametrisation (s=1: var_p = c, b = sigma_0^2)."""
    p = gpr.kernel_.get_params()
    var_m = p["k1__k1__k1__constant_value"]
    ls = p["k1__k1__k2__length_scale"]
    c = p["k1__k2__k1__constant_value"]
    s0 = p["k1__k2__k2__kernel__sigma_0"]
    nv = p["k2__noise_level"]
    return np.log([var_m, ls, c, 1.0, s0 ** 2, nv])


def main():
    def extra(ap):
        ap.add_argument("--restarts", type=int, default=None,
                        help="also time the default fit with this many seeded restarts (default 0: skipped)")
        ap.add_argument("--sizes", default="1000,2000,4000", help="comma-separated N (default 1000,2000,4000)")

    args = C.parse_args(__doc__, extra)
    restarts = args.restarts if args.restarts is not None else 0
    sizes = (100, 200) if args.quick else tuple(int(s) for s in args.sizes.split(","))
    max_iter = 30 if args.quick else None  # quick: capped L-BFGS-B iterations on both sides (smoke test only)
    it = {"max_iter": max_iter} if max_iter else {}
    rows = []
    print(f"bench_fit: ML-II, eq. (12) kernel, D={C.D}, one start each; {C.env_note()}")
    print(f"  {'N':>5} {'cold s':>8} {'default s':>9} {'sklearn s':>9} {'ratio':>6} {'ratio cold':>10} "
          f"{'cold NLML':>11} {'default NLML':>12} {'sklearn NLML':>12} {'ours NLML @ sk opt':>18} "
          f"{'evals cold/default(+subset)/sk':>30} {'s/eval cold/sk':>15}")
    for n in sizes:
        X, y, _, _ = C.training_set(n)
        k = make_kernel("matern32+cubic")
        theta0 = initial_theta(k, X, y)
        EVALS.update(sklearn=0)
        sub = default_warm_start_subset(n) if not args.quick else n // 4
        t0 = time.perf_counter()
        cold = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0, seed=0, **it)
        cold_s = time.perf_counter() - t0
        gpr, sk_s = sk_fit(theta0, X, y, max_iter)
        if sub:
            t0 = time.perf_counter()
            res = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0, seed=0, warm_start_subset=sub,
                          hold_redundant=True, **it)
            ours_s = time.perf_counter() - t0
        else:
            res, ours_s = cold, cold_s
        ev_s = EVALS["sklearn"]
        sk_nlml = -float(gpr.log_marginal_likelihood_value_)
        ours_at_sk = nlml_and_grad(sk_theta_as_ours(gpr), make_kernel("matern32+cubic"), X, y)[0]
        rr = None
        if restarts:
            t0 = time.perf_counter()
            r2 = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=restarts, seed=0,
                         warm_start_subset=sub, hold_redundant=bool(sub))
            rr = (time.perf_counter() - t0, r2.nlml, r2.restarts)
        rows.append((n, ours_s, sk_s, res.nlml, sk_nlml, ours_at_sk, res.theta, gpr.kernel_, rr, cold_s, cold.nlml,
                     sub))
        evs = f"{cold.n_evals}/{res.n_evals}(+{res.subset_evals}@{res.subset_rows})/{ev_s}"
        print(f"  {n:>5} {cold_s:8.2f} {ours_s:9.2f} {sk_s:9.2f} {sk_s / ours_s:6.2f} {sk_s / cold_s:10.2f} "
              f"{cold.nlml:11.2f} {res.nlml:12.2f} {sk_nlml:12.2f} {ours_at_sk:18.2f} {evs:>30} "
              f"{cold_s / max(cold.n_evals, 1):7.3f}/{sk_s / max(ev_s, 1):<7.3f}", flush=True)
        if rr:
            print(f"        ours with n_restarts={restarts}: {rr[0]:.2f} s (x{sk_s / rr[0]:.2f} vs sklearn), NLML "
                  f"{rr[1]:.2f}; starts (NLML, iterations): "
                  + ", ".join(f"({a:.2f}, {b})" for a, b in rr[2]), flush=True)
    n, ours_s, sk_s, nlml, sk_nlml, _, theta, skk, rr, cold_s, cold_nlml, sub = rows[-1]
    print(f"  largest N={n}: ours theta (natural units) {np.round(np.exp(theta), 6).tolist()}")
    print(f"  sklearn kernel_: {skk}")
    print(f"  NLML difference (sklearn - ours default) at N={n}: {sk_nlml - nlml:+.3f} nats "
          f"({'ours equal or better' if sk_nlml - nlml >= -1e-3 * abs(nlml) - 1e-6 else 'sklearn better'}); "
          f"cold: {sk_nlml - cold_nlml:+.3f} nats")
    kv = {}
    for r in rows:
        kv[f"fit_s_{r[0]}"] = r[1]
    kv.update(baseline=sk_s, ratio=sk_s / ours_s, nlml=nlml, baseline_nlml=sk_nlml, fit_s_cold=cold_s,
              ratio_cold=sk_s / cold_s, nlml_cold=cold_nlml, warm_start_subset=sub or 0)
    for r in rows[:-1]:
        kv[f"ratio_{r[0]}"] = r[2] / r[1]
    if rr:
        kv.update({"fit_s_restarts": rr[0], "ratio_restarts": sk_s / rr[0], "nlml_restarts": rr[1],
                   "restarts": restarts})
    kv["N"] = n
    kv["load"] = C.load()
    kv["blas_threads"] = C.blas_threads()
    if not math.isfinite(kv["ratio"]):
        raise SystemExit("non-finite ratio")
    C.result(**kv)


if __name__ == "__main__":
    main()
