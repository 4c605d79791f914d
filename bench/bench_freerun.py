"""Monte Carlo free-run throughput, exact mode: path-steps per second, 1024 paths, N=2000, D=37.

Product: ``model.freerun.simulate_mc`` on our ``ExactPosterior``: all paths advance together, one
kernel block K(X_paths, X) and one triangular BLAS-3 product (dtrmm, P N^2 flops) for the variances
per step. Also timed: a dense-dgemm variance product (2 P N^2 flops), as a reference.
Baseline: the per-step loop a user would write around scikit-learn's
``GaussianProcessRegressor.predict(X_paths, return_std=True)`` with the same kernel (eq. 12),
hyperparameters and training points, sampling y ~ N(mu, std^2 + noise) and feeding it back.

Both run the same segment of the Bouc-Wen 50 N sweep from the same measured initial lags with the
same seed, interleaved (ours, baseline, ours float32) over several repetitions, in one process (same
BLAS threads and malloc); ``ratio=`` is the median of the per-repetition ratios (same N, float64:
equal work). ``f32_ratio`` is NOT equal precision (our float32 variance product against scikit-learn
in float64). Means are checked equal on identical regressor blocks.
Hyperparameters: ML-II (one start) on a stride subset (timings do not depend on their values).

    python bench/bench_freerun.py [--quick]
"""
from __future__ import annotations

import time

import numpy as np
from scipy import linalg

import _common as C
from gpnarx.model.freerun import simulate_mc

# equal work with the exact baselines: every Monte Carlo run here passes local=False, so the product evaluates
# eq. 8-9 at every path (its default checked local model is compared like for like in bench_mc_speed.py)


class GemmPosterior:
    """Reference, NOT the product: our exact posterior with the variance product done by a dense dgemm.

    This is what ``ExactPosterior.predict`` did before it used dtrmm: V = Ks @ Linv.T, 2 P N^2 flops,
    where the triangular product needs P N^2. Same kernel block, same mean; kept to show the gain
    in the same run.
    """

    def __init__(self, post):
        self.post = post
        self.noise_var = post.noise_var

    def predict(self, Xs, return_var=True, float32=False):
        p = self.post
        Ks = p.cross(Xs)
        mean = Ks @ p.alpha
        V = Ks @ p.Linv.T
        var = p.kernel.diag(Xs) - np.einsum("ij,ij->i", V, V)
        np.maximum(var, 1e-300, out=var)
        return mean, var


def step_profile(post, gpr, Xb, repeat=3):
    """Seconds of each part of one step for a (P, D) block: ours, sklearn's, and alternatives."""
    out = {}
    X = post.points
    k = post.kernel
    t, G = C.best(lambda: Xb @ X.T, repeat)
    out["ours: Gram Xs @ X.T (dgemm P x D x N)"] = t
    sq1 = np.einsum("ij,ij->i", Xb, Xb)
    sqX = np.einsum("ij,ij->i", X, X)  # the posterior keeps these; computed once here, outside the timing
    t, Ks = C.best(lambda: k.from_gram(G, sq1, sqX), repeat)
    out["ours: kernel elementwise (Matern sqrt/exp + cubic)"] = t
    out["ours: mean Ks @ alpha (gemv)"] = C.best(lambda: Ks @ post.alpha, repeat)[0]
    LT = np.ascontiguousarray(post.Linv.T)
    t, V = C.best(lambda: Ks @ post.Linv.T, repeat)
    out["reference: variance Ks @ Linv.T (dense dgemm, 2PN^2)"] = t
    out["ours: rowwise |V|^2 (einsum)"] = C.best(lambda: np.einsum("ij,ij->i", V, V), repeat)[0]
    out["ours: kernel diag"] = C.best(lambda: k.diag(Xb), repeat)[0]
    out["ours: whole predict()"] = C.best(lambda: post.predict(Xb), repeat)[0]
    out["ours: whole predict(float32=True)"] = C.best(lambda: post.predict(Xb, float32=True), repeat)[0]
    out["sklearn: kernel_(X, X_train) (cdist + powers)"] = C.best(lambda: gpr.kernel_(Xb, gpr.X_train_), repeat)[0]
    Kt = gpr.kernel_(Xb, gpr.X_train_)
    out["sklearn: solve_triangular L \\ K^T (dtrsm, PN^2)"] = C.best(
        lambda: linalg.solve_triangular(gpr.L_, Kt.T, lower=True, check_finite=False), repeat)[0]
    out["sklearn: whole predict(return_std=True)"] = C.best(lambda: gpr.predict(Xb, return_std=True), repeat)[0]
    # alternatives the product could use (model/ is not edited here; figures for the proposal)
    out["ours: variance dtrmm Linv @ Ks^T (triangular, PN^2)"] = C.best(
        lambda: linalg.blas.dtrmm(1.0, post.Linv.T, Ks.T, side=0, lower=0, trans_a=1), repeat)[0]
    Linv32 = np.asfortranarray(post.Linv, dtype=np.float32)
    KsT32 = np.asfortranarray(Ks.T, dtype=np.float32)
    out["alt: strmm float32 (triangular, PN^2)"] = C.best(
        lambda: linalg.blas.strmm(1.0, Linv32, KsT32, side=0, lower=1), repeat)[0]
    LT32 = LT.astype(np.float32)
    Ks32 = Ks.astype(np.float32)
    out["alt: sgemm float32 Ks @ Linv.T (dense)"] = C.best(lambda: Ks32 @ LT32, repeat)[0]
    out["alt: Ks.astype(float32) cast"] = C.best(lambda: Ks.astype(np.float32), repeat)[0]
    return out


def main():
    args = C.parse_args(__doc__)
    q = args.quick
    N = 500 if q else 2000
    P = 256 if q else 1024
    steps = 5 if q else 20
    reps = 2 if q else 4

    t0 = time.perf_counter()
    theta, fit_s, hyp = C.hyperparameters(q)
    X, y, xsc, ysc = C.training_set(N)
    post = C.exact_posterior(theta, X, y)
    gpr = C.sk_gpr(theta, X, y)
    noise = float(np.exp(theta[-1]))
    r50 = C.protocol()[2]
    i0 = 900  # a segment of the 50 N sweep (about 20 Hz, below the resonance) from measured lags
    u = r50.u[i0: i0 + C.NY + steps].copy()
    y0 = r50.y[i0: i0 + C.NY].copy()
    setup_s = time.perf_counter() - t0

    # warm-up (BLAS threads, caches, first-call imports)
    simulate_mc(post, xsc, ysc, C.NY, C.NU, u[: C.NY + 2], n_paths=P, seed=0, y0=y0, local=False)
    simulate_mc(post, xsc, ysc, C.NY, C.NU, u[: C.NY + 2], n_paths=P, seed=0, y0=y0, float32=True, local=False)
    C.sklearn_freerun(gpr, noise, xsc, ysc, u[: C.NY + 2], y0, P, seed=0)

    alt = GemmPosterior(post)
    simulate_mc(alt, xsc, ysc, C.NY, C.NU, u[: C.NY + 2], n_paths=P, seed=0, y0=y0, local=False)
    ours_t, base_t, f32_t, gemm_t, dg = [], [], [], [], []
    keep = (C.NY, C.NY + steps // 2, C.NY + steps - 1)
    for r in range(reps):
        dg.append(C.dgemm_gflops(N, P, repeat=2))
        fr = simulate_mc(post, xsc, ysc, C.NY, C.NU, u, n_paths=P, seed=r, y0=y0, local=False)
        ours_t.append(fr.seconds)
        bm, blo, bhi, bs, bsteps, kept = C.sklearn_freerun(gpr, noise, xsc, ysc, u, y0, P, seed=r, keep_X=keep)
        base_t.append(bs)
        fr32 = simulate_mc(post, xsc, ysc, C.NY, C.NU, u, n_paths=P, seed=r, y0=y0, float32=True, local=False)
        f32_t.append(fr32.seconds)
        frg = simulate_mc(alt, xsc, ysc, C.NY, C.NU, u, n_paths=P, seed=r, y0=y0, local=False)
        gemm_t.append(frg.seconds)
    path_steps = fr.path_steps
    assert path_steps == bsteps == steps * P

    # means: identical regressor blocks through both predictors (standardised units)
    diffs, var_rel, var_rel32, sd_rel32, gemm_diff = [], [], [], [], []
    for Xb in kept.values():
        m1, v1 = post.predict(Xb)
        m2, s2 = gpr.predict(Xb, return_std=True)
        _, v32 = post.predict(Xb, float32=True)
        diffs.append(np.max(np.abs(m1 - m2)))
        var_rel.append(np.max(np.abs(v1 - s2 ** 2) / v1))
        var_rel32.append(np.max(np.abs(v32 - v1) / v1))
        s1, s32 = np.sqrt(v1 + noise), np.sqrt(v32 + noise)
        sd_rel32.append(np.max(np.abs(s32 - s1) / s1))
        gemm_diff.append(np.max(np.abs(alt.predict(Xb.copy())[1] - v1) / v1))
    max_mean_diff = float(max(diffs))
    # same seed, same random numbers: the two free-runs should also agree (output units, m)
    freerun_mean_diff = float(np.max(np.abs(fr.mean - bm)))

    ratios = [b / o for o, b in zip(ours_t, base_t)]
    ratios32 = [b / o for o, b in zip(f32_t, base_t)]
    ratios_gemm = [b / o for o, b in zip(gemm_t, base_t)]
    ours_ps = path_steps / C.median(ours_t)
    base_ps = path_steps / C.median(base_t)
    f32_ps = path_steps / C.median(f32_t)
    flops_step = 2.0 * P * N * C.D + 1.0 * P * N * N
    gflops = flops_step * steps / C.median(ours_t) / 1e9
    dgemm = max(dg)

    print(f"bench_freerun: exact GP, N={N}, D={C.D}, {P} paths x {steps} steps, {reps} interleaved reps "
          f"(setup {setup_s:.1f} s; hyperparameters: {hyp}; {C.env_note()})")
    print(f"  {'rep':>3} {'ours s':>8} {'sklearn s':>9} {'ours f32 s':>10} {'prev dgemm s':>12} "
          f"{'ratio':>6} {'ratio f32':>9} {'ratio dgemm':>11}")
    for r in range(reps):
        print(f"  {r:>3} {ours_t[r]:8.3f} {base_t[r]:9.3f} {f32_t[r]:10.3f} {gemm_t[r]:12.3f} "
              f"{ratios[r]:6.2f} {ratios32[r]:9.2f} {ratios_gemm[r]:11.2f}")
    print(f"  path-steps/s: ours {ours_ps:,.0f}  sklearn {base_ps:,.0f}  ours float32 {f32_ps:,.0f}  "
          f"dense dgemm (reference) {path_steps / C.median(gemm_t):,.0f}")
    print(f"  max |mean diff| (standardised, same X blocks) {max_mean_diff:.2e}; max var rel diff {max(var_rel):.2e}; "
          f"free-run mean diff (same seed) {freerun_mean_diff:.2e} m; dense dgemm var rel diff {max(gemm_diff):.1e}")
    print(f"  float32: max latent-variance rel err {max(var_rel32):.2e}, max predictive-std (incl. noise) rel err "
          f"{max(sd_rel32):.2e} (latent var = k(x,x) - |Linv k|^2 cancels: k(x,x) ~ "
          f"{float(np.median(post.kernel.diag(Xb))):.3g}, var ~ {float(np.median(post.predict(Xb)[1])):.2g})")
    print(f"  achieved {gflops:.1f} GFLOP/s (2PND + PN^2 per step) vs numpy dgemm {dgemm:.1f} GFLOP/s "
          f"({100 * gflops / dgemm:.0f}%)")

    Xb = kept[keep[1]]
    prof = step_profile(post, gpr, Xb, repeat=3 if q else 5)
    print(f"  one-step profile, P={P}, N={N} (best of repeats, ms):")
    for name, t in prof.items():
        print(f"    {name:<55} {1e3 * t:8.2f}")

    C.result(path_steps_per_s=ours_ps, baseline=base_ps, baseline_what=f"sklearn-exact-N{N}", ratio=C.median(ratios),
             max_mean_diff=max_mean_diff,
             gflops=gflops, dgemm_gflops=dgemm, f32_path_steps_per_s=f32_ps, f32_ratio=C.median(ratios32),
             f32_max_var_rel_err=max(var_rel32), f32_max_std_rel_err=max(sd_rel32),
             prev_dgemm_ratio=C.median(ratios_gemm), speedup_vs_dgemm=C.median(gemm_t) / C.median(ours_t),
             ratio_best=min(base_t) / min(ours_t), N=N, paths=P, steps=steps, load=C.load(),
             blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
