"""Cost growth: log-log slopes against training points N, Monte Carlo paths and record length.

Measured (best of a few repeats each, Bouc-Wen protocol, D=37, eq. 12 kernel, fixed hyperparameters):
  * fit vs N: one NLML + analytic-gradient evaluation (``model.ml2.nlml_and_grad``), the unit cost of
    every ML-II iteration (iteration counts vary with the data, so the whole fit is not used here);
  * step vs N: one Monte Carlo step, ``ExactPosterior.predict`` on a (P, D) block (P=1024);
  * paths: one step at fixed N against P;
  * record length: ``simulate_mc`` wall time against the number of steps (fixed N and P).
Baseline: scikit-learn ``GaussianProcessRegressor.predict(X, return_std=True)`` per step against N
(same kernel, hyperparameters, points and block, float64, same process), interleaved with ours at
each N. Slopes are ``np.polyfit(log x, log t, 1)`` of the best time per size. ``ratio=`` (equal
work) = median over the interleaved repetitions of baseline step time / ours at the largest N.

    python bench/bench_scaling.py [--quick] [--threads T]
"""
from __future__ import annotations

import numpy as np

import _common as C
from gpnarx.model.freerun import simulate_mc
from gpnarx.model.kernels import make_kernel
from gpnarx.model.ml2 import nlml_and_grad

# equal work with the exact baselines: every Monte Carlo run here passes local=False, so the product evaluates
# eq. 8-9 at every path (its default checked local model is compared like for like in bench_mc_speed.py)


def main():
    args = C.parse_args(__doc__)
    q = args.quick
    Ns = (100, 200, 400) if q else (500, 1000, 2000, 4000)
    P = 256 if q else 1024
    Ps = (64, 128, 256) if q else (128, 256, 512, 1024, 2048)
    N_paths = 200 if q else 1000
    lengths = (5, 10, 20) if q else (10, 20, 40, 80)
    N_len, P_len = (200, 64) if q else (1000, 256)
    rep = 2 if q else 4
    theta = C.THETA_REF  # fixed reference hyperparameters (ML-II on 500 points): timing does not depend on them
    hyp = "hyperparameters THETA_REF"
    rng = np.random.default_rng(0)

    def block(X, p):
        """A realistic (p, D) regressor block: training rows plus a small perturbation."""
        return X[rng.integers(0, X.shape[0], p)] + 0.05 * rng.standard_normal((p, X.shape[1]))

    fit_t, step_t, base_t, step_ratio = [], [], [], []
    for n in Ns:
        X, y, _, _ = C.training_set(n)
        k = make_kernel("matern32+cubic")
        fit_t.append(C.best(lambda k=k, X=X, y=y: nlml_and_grad(theta, k, X, y), rep)[0])
        post = C.exact_posterior(theta, X, y)
        gpr = C.sk_gpr(theta, X, y)
        Xb = block(X, P)
        post.predict(Xb)
        gpr.predict(Xb, return_std=True)
        t_o, t_b = [], []
        for _ in range(rep):  # interleaved
            t_o.append(C.best(lambda post=post, Xb=Xb: post.predict(Xb), 1)[0])
            t_b.append(C.best(lambda gpr=gpr, Xb=Xb: gpr.predict(Xb, return_std=True), 1)[0])
        step_t.append(min(t_o))
        base_t.append(min(t_b))
        step_ratio.append(C.median_ratio(t_b, t_o))

    X, y, xsc, ysc = C.training_set(N_paths)
    post = C.exact_posterior(theta, X, y)
    blocks = {p: block(X, p) for p in Ps}
    post.predict(blocks[Ps[-1]])
    path_all = {p: [] for p in Ps}
    for _ in range(rep):  # round-robin over sizes so a load change hits all of them
        for p in Ps:
            path_all[p].append(C.best(lambda p=p: post.predict(blocks[p]), 1)[0])
    path_t = [min(path_all[p]) for p in Ps]

    X, y, xsc, ysc = C.training_set(N_len)
    post = C.exact_posterior(theta, X, y)
    r50 = C.protocol()[2]
    simulate_mc(post, xsc, ysc, C.NY, C.NU, r50.u[500:502], n_paths=P_len, seed=0, local=False)
    len_all = {L: [] for L in lengths}
    for _ in range(rep):  # round-robin
        for L in lengths:
            u = r50.u[500: 500 + L]
            len_all[L].append(simulate_mc(post, xsc, ysc, C.NY, C.NU, u, n_paths=P_len, seed=0, local=False).seconds)
    len_t = [min(len_all[L]) for L in lengths]

    s_fit = C.loglog_slope(Ns, fit_t)
    s_step = C.loglog_slope(Ns, step_t)
    s_base = C.loglog_slope(Ns, base_t)
    s_paths = C.loglog_slope(Ps, path_t)
    s_len = C.loglog_slope(lengths, len_t)
    # slopes over the upper half of N, where the O(N^2)/O(N^3) terms dominate
    hi = slice(len(Ns) // 2, None)
    s_step_hi = C.loglog_slope(Ns[hi], step_t[hi]) if len(Ns[hi]) >= 2 else s_step
    s_base_hi = C.loglog_slope(Ns[hi], base_t[hi]) if len(Ns[hi]) >= 2 else s_base
    s_fit_hi = C.loglog_slope(Ns[hi], fit_t[hi]) if len(Ns[hi]) >= 2 else s_fit

    print(f"bench_scaling: D={C.D}, eq. (12) kernel, {hyp}; {C.env_note()}")
    print(f"  {'N':>5} {'NLML+grad s':>11} {'ours step s':>11} {'sklearn step s':>14} {'ratio':>6}   (P={P}; best "
          f"times; ratio: median of {rep} interleaved repetitions)")
    for n, a, b, c, r in zip(Ns, fit_t, step_t, base_t, step_ratio):
        print(f"  {n:>5} {a:11.4f} {b:11.4f} {c:14.4f} {r:6.2f}")
    print(f"  paths at N={N_paths}: " + ", ".join(f"P={p}: {t * 1e3:.1f} ms" for p, t in zip(Ps, path_t)))
    print(f"  record length at N={N_len}, P={P_len}: "
          + ", ".join(f"{L} steps: {t:.3f} s" for L, t in zip(lengths, len_t)))
    print(f"  log-log slopes: fit(NLML+grad) vs N {s_fit:.2f} (upper half {s_fit_hi:.2f}); step vs N ours {s_step:.2f} "
          f"(upper half {s_step_hi:.2f}), sklearn {s_base:.2f} (upper half {s_base_hi:.2f}); "
          f"step vs paths {s_paths:.2f}; run vs length {s_len:.2f}")
    C.result(slope_N_fit=s_fit, slope_N_step=s_step, slope_paths=s_paths, slope_length=s_len, baseline=s_base,
             baseline_what="sklearn-exact-predict-same-N-same-block",
             ratio=step_ratio[-1], step_s=step_t[-1], baseline_step_s=base_t[-1], slope_N_fit_hi=s_fit_hi,
             slope_N_step_hi=s_step_hi,
             baseline_hi=s_base_hi, N_max=Ns[-1], load=C.load(), blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
