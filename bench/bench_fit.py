"""ML-II cost against N: ours vs scikit-learn's GaussianProcessRegressor.

Both sides work on the same standardised Bouc-Wen training rows (stride selection), the eq. (12)
kernel, in the same process (same BLAS threads and malloc), float64.

Equal work (``ratio=``): one NLML + gradient evaluation, the unit of every ML-II iteration, at the
largest N, from the same data-scaled hyperparameters. Ours: ``model.ml2.nlml_and_grad`` with the
reused ``NLMLWorkspace`` (one Cholesky, one potri, analytic gradient traces), as ``fit_ml2`` calls
it; baseline: ``GaussianProcessRegressor.log_marginal_likelihood(theta, eval_gradient=True)``, as
scikit-learn's optimiser calls it, with the same kernel written ``C*Matern(nu=1.5) +
C*DotProduct**3 + WhiteKernel`` (5 log-parameters against our 6: our cubic scale s is redundant).
Repetitions interleaved (ours, sklearn, ours, ...; below N=2000 each timing averages 2000 // N
evaluations); ratio = median of sklearn time / ours.

Whole fits (one start, data-scaled initial point, interleaved with each other per repetition):
* ``plain``: ours ``fit_ml2`` with the optimiser settings scikit-learn's default optimiser uses
  (scipy L-BFGS-B, its default iteration limit and tolerances, no stall stop, no warm start), all 6
  parameters free; ``fit_ratio_plain`` = sklearn fit time / this (same algorithm and start; each
  side's own parametrisation and bounds, so the evaluation counts differ and are printed);
* ``default``: what ``GPNARX`` runs (from N=2000 the start is first optimised on N/4 strided rows,
  ``warm_start_subset``, the redundant cubic scale s is held, ``hold_redundant``, and L-BFGS-B ends
  on a 10-evaluation stall or 200 iterations); ``user_ratio`` = sklearn fit time / this, labelled
  ``user_baseline``: NOT equal work (different optimiser strategy), it is what a user of scikit-learn
  would otherwise run;
* sklearn: ``fit`` with its own optimiser (fmin_l_bfgs_b, n_restarts_optimizer=0), started from the
  same hyperparameters, bounds wide enough to contain our optimum (sklearn's defaults would clip
  the cubic amplitude, about 1e-12 here).
NLMLs are comparable: sklearn's WhiteKernel plays our noise variance (its default alpha=1e-10 adds
a negligible jitter); sklearn's optimum is also re-evaluated with our NLML as a cross-check.

    python bench/bench_fit.py [--quick] [--threads N] [--sizes 1000,2000,4000] [--restarts R] [--fit-reps R]
"""
from __future__ import annotations

import math
import time
import warnings

import numpy as np
from scipy.optimize import minimize

import _common as C
from gpnarx.model.kernels import make_kernel
from gpnarx.model.ml2 import NLMLWorkspace, default_warm_start_subset, fit_ml2, initial_theta, nlml_and_grad

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


def sk_fixed(theta0, X, y):
    """sklearn GPR with the fit kernel (free bounds, WhiteKernel) at theta0, fitted without optimising."""
    from sklearn.gaussian_process import GaussianProcessRegressor

    gpr = GaussianProcessRegressor(C.sk_kernel(theta0, fixed=False, white=True), optimizer=None, normalize_y=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gpr.fit(X, y)
    return gpr


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
        ap.add_argument("--fit-reps", type=int, default=1,
                        help="interleaved repetitions of the whole fits (default 1; a fit at N=4000 takes minutes)")
        ap.add_argument("--eval-reps", type=int, default=None,
                        help="interleaved repetitions of one NLML + gradient evaluation (default 5; 3 with --quick)")

    args = C.parse_args(__doc__, extra)
    restarts = args.restarts if args.restarts is not None else 0
    sizes = (100, 200) if args.quick else tuple(int(s) for s in args.sizes.split(","))
    # plain fits use L-BFGS-B's defaults on both sides (scipy: maxiter 15000); quick caps both at 30
    max_iter = 30 if args.quick else 15000
    eval_reps = args.eval_reps or (3 if args.quick else 5)
    fit_reps = max(1, args.fit_reps)
    rows = []
    print(f"bench_fit: ML-II, eq. (12) kernel, D={C.D}, one start each; {C.env_note()}")
    print(f"  {'N':>5} {'eval ours s':>11} {'eval sk s':>9} {'ratio':>6} {'plain s':>8} {'default s':>9} "
          f"{'sklearn s':>9} {'plain r':>7} {'user r':>6} {'plain NLML':>11} {'default NLML':>12} {'sklearn NLML':>12} "
          f"{'ours NLML @ sk opt':>18} {'evals plain/default(+subset)/sk':>31}")
    for n in sizes:
        X, y, _, _ = C.training_set(n)
        k = make_kernel("matern32+cubic")
        theta0 = initial_theta(k, X, y)
        sub = default_warm_start_subset(n) if not args.quick else n // 4

        # equal work: one NLML + gradient evaluation each, interleaved
        ws = NLMLWorkspace(k, X)
        gpr0 = sk_fixed(theta0, X, y)
        th_sk = gpr0.kernel_.theta.copy()

        inner = max(1, 2000 // n)  # small N: several evaluations per timing, so one lost time slice does not decide

        def ours_eval(k=k, X=X, y=y, ws=ws, theta0=theta0, inner=inner):
            t0 = time.perf_counter()
            for _ in range(inner):
                nlml_and_grad(theta0, k, X, y, ws)
            return (time.perf_counter() - t0) / inner

        def sk_eval(gpr0=gpr0, th_sk=th_sk, inner=inner):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for _ in range(inner):
                    gpr0.log_marginal_likelihood(th_sk, eval_gradient=True, clone_kernel=False)
            return (time.perf_counter() - t0) / inner

        ours_eval(), sk_eval()  # warm-up
        ev = C.interleave({"ours": ours_eval, "sklearn": sk_eval}, eval_reps)
        eval_ratio = C.median_ratio(ev["sklearn"], ev["ours"])
        del ws, gpr0

        # whole fits, interleaved per repetition
        out = {}

        def plain(X=X, y=y):
            t0 = time.perf_counter()
            r = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0, seed=0, max_iter=max_iter,
                        stall_evals=None)
            return time.perf_counter() - t0, r

        def sklearn(theta0=theta0, X=X, y=y):
            EVALS.update(sklearn=0)
            gpr, s = sk_fit(theta0, X, y, max_iter)
            return s, (gpr, EVALS["sklearn"])

        def default(X=X, y=y, sub=sub):
            t0 = time.perf_counter()
            it = {"max_iter": max_iter} if args.quick else {}
            r = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0, seed=0, warm_start_subset=sub,
                        hold_redundant=bool(sub), **it)
            return time.perf_counter() - t0, r

        out = C.interleave({"plain": plain, "sklearn": sklearn, "default": default}, fit_reps)
        plain_s = C.median([t for t, _ in out["plain"]])
        sk_s = C.median([t for t, _ in out["sklearn"]])
        ours_s = C.median([t for t, _ in out["default"]])
        fit_ratio_plain = C.median_ratio([t for t, _ in out["sklearn"]], [t for t, _ in out["plain"]])
        user_ratio = C.median_ratio([t for t, _ in out["sklearn"]], [t for t, _ in out["default"]])
        cold, res = out["plain"][-1][1], out["default"][-1][1]
        gpr, ev_s = out["sklearn"][-1][1]
        sk_nlml = -float(gpr.log_marginal_likelihood_value_)
        ours_at_sk = nlml_and_grad(sk_theta_as_ours(gpr), make_kernel("matern32+cubic"), X, y)[0]
        rr = None
        if restarts:
            t0 = time.perf_counter()
            r2 = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=restarts, seed=0,
                         warm_start_subset=sub, hold_redundant=bool(sub))
            rr = (time.perf_counter() - t0, r2.nlml, r2.restarts)
        rows.append(dict(n=n, eval_ours=C.median(ev["ours"]), eval_sk=C.median(ev["sklearn"]), eval_ratio=eval_ratio,
                         plain_s=plain_s, sk_s=sk_s, ours_s=ours_s, fit_ratio_plain=fit_ratio_plain,
                         user_ratio=user_ratio, nlml=res.nlml, sk_nlml=sk_nlml, cold_nlml=cold.nlml, theta=res.theta,
                         skk=gpr.kernel_, rr=rr, sub=sub))
        evs = f"{cold.n_evals}/{res.n_evals}(+{res.subset_evals}@{res.subset_rows})/{ev_s}"
        print(f"  {n:>5} {C.median(ev['ours']):11.4f} {C.median(ev['sklearn']):9.4f} {eval_ratio:6.2f} {plain_s:8.2f} "
              f"{ours_s:9.2f} {sk_s:9.2f} {fit_ratio_plain:7.2f} {user_ratio:6.2f} {cold.nlml:11.2f} {res.nlml:12.2f} "
              f"{sk_nlml:12.2f} {ours_at_sk:18.2f} {evs:>31}", flush=True)
        if rr:
            print(f"        ours with n_restarts={restarts}: {rr[0]:.2f} s (x{sk_s / rr[0]:.2f} vs sklearn), NLML "
                  f"{rr[1]:.2f}; starts (NLML, iterations): "
                  + ", ".join(f"({a:.2f}, {b})" for a, b in rr[2]), flush=True)
    last = rows[-1]
    n = last["n"]
    print(f"  (ratio: one NLML+gradient evaluation, median of {eval_reps} interleaved repetitions; plain r = sklearn "
          f"fit / ours plain; user r = sklearn fit / ours default; whole fits: median of {fit_reps} interleaved "
          f"repetition(s))")
    print(f"  largest N={n}: ours default theta (natural units) {np.round(np.exp(last['theta']), 6).tolist()}")
    print(f"  sklearn kernel_: {last['skk']}")
    print(f"  NLML difference (sklearn - ours default) at N={n}: {last['sk_nlml'] - last['nlml']:+.3f} nats; "
          f"(sklearn - ours plain): {last['sk_nlml'] - last['cold_nlml']:+.3f} nats")
    kv = dict(eval_s=last["eval_ours"], baseline=last["eval_sk"], baseline_what="sklearn-lml-eval-grad-same-N",
              ratio=last["eval_ratio"])
    for r in rows[:-1]:
        kv[f"ratio_{r['n']}"] = r["eval_ratio"]
    kv.update(fit_s_plain=last["plain_s"], fit_s_default=last["ours_s"], baseline_fit_s=last["sk_s"],
              fit_ratio_plain=last["fit_ratio_plain"], user_baseline="sklearn-fit-lbfgsb-vs-GPNARX-default",
              user_ratio=last["user_ratio"], nlml=last["nlml"], nlml_plain=last["cold_nlml"],
              baseline_nlml=last["sk_nlml"], warm_start_subset=last["sub"] or 0)
    for r in rows:
        kv[f"fit_s_{r['n']}"] = r["ours_s"]
    if last["rr"]:
        rr = last["rr"]
        kv.update({"fit_s_restarts": rr[0], "user_ratio_restarts": last["sk_s"] / rr[0], "nlml_restarts": rr[1],
                   "restarts": restarts})
    kv.update(N=n, eval_reps=eval_reps, fit_reps=fit_reps, load=C.load(), blas_threads=C.blas_threads())
    if not math.isfinite(kv["ratio"]):
        raise SystemExit("non-finite ratio")
    C.result(**kv)


if __name__ == "__main__":
    main()
