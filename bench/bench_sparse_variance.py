"""Sparse eq. (9) variance: accuracy and cost of the factored form |G k|^2 against k^T A k.

The product (``SparsePosterior``) stores G with A = Kmm^-1 - Sigma^-1 = G^T G and computes the
latent variance as k(x,x) - |G k|^2 (docs/numerics.md, safeguard 2). The baseline is the
single-matrix form k(x,x) - k^T A k on the same posterior (``legacy_A``: what a bundle storing A
itself does). Reference: an independent evaluation k(x,x) - |Lm^-1 k|^2 + |R^-T k|^2 with
Sigma = R^T R from the QR factorisation of [Lm^T; Knm / sigma] (no Gram product, no explicit
inverse), in float64.

Case: the Bouc-Wen training rows (10 N and 80 N sweeps, ny=20, nu=17, D=37, 4064 rows, M=512
k-means inducing points) with hyperparameters shaped like the real-BERT ML-II optimum, where the
noise variance sits at ML-II's 1e-8 floor: Matérn variance 1e-3 and length scale 12.9, cubic
sigma_p^2 0.017, s 3.7e-5, b 70.9 (constant capped at 1 for the variance, as the product does).
Queries: 1024 rows of the 50 N sweep (standardised). Printed: the median relative error of each
form against the reference (built with one BLAS thread), the largest relative change when the
posterior is built and evaluated with 2 BLAS threads instead of 1, and the time of one
1024-row predict (median of interleaved repetitions; ratio = factored / single-matrix time, so
1.0 means the same cost).

Baseline (no scikit-learn equivalent; equal work): the single-matrix form on the same posterior,
same M, queries, float64 and BLAS threads, in the same process, interleaved. Note that this ratio
is product / baseline TIME (lower is better), unlike the throughput ratios of the other benches.

    python bench/bench_sparse_variance.py [--quick] [--threads N]
"""
from __future__ import annotations

import time

import numpy as np
from threadpoolctl import threadpool_limits

import _common as C
from gpnarx.model.gp import SparsePosterior, choose_inducing, sparse_variance_reference
from gpnarx.model.kernels import make_kernel
from gpnarx.model.regressors import stack_regressors

THETA_FLOOR = np.log([1e-3, 12.9, 0.017, 3.7e-5, 70.9, 1e-8])


def main() -> None:
    args = C.parse_args(__doc__)
    m = 128 if args.quick else 512
    n_query = 256 if args.quick else 1024
    reps = 3 if args.quick else 9
    X, y, xsc, _ = C.training_set(1000 if args.quick else C.n_rows())
    kernel = make_kernel("matern32+cubic")
    kernel.set_theta(THETA_FLOOR[:-1])
    var_kernel = kernel.for_posterior(1.0)
    noise_var = float(np.exp(THETA_FLOOR[-1]))
    Z = choose_inducing(X, m, 0)
    _, _, r50 = C.protocol()
    Xq_raw, _, _ = stack_regressors([(r50.u, r50.y)], C.NY, C.NU)
    Xq = np.ascontiguousarray(xsc.transform(Xq_raw)[200:200 + n_query])
    # build and predict under 1 and then 2 BLAS threads: the single-matrix form's error comes
    # mostly from building A (its products and inverses sum in a thread-dependent order)
    forms = {}
    for n in (1, 2):
        with threadpool_limits(limits=n, user_api="blas"):
            t0 = time.perf_counter()
            post = SparsePosterior.fit(kernel, noise_var, X, y, Z, var_kernel=var_kernel)
            build_s = time.perf_counter() - t0
            old = SparsePosterior(post.kernel, noise_var, post.points, post.w, legacy_A=post.A)
            forms[n] = {"factored": (post, post.predict(Xq)[1]), "single": (old, old.predict(Xq)[1])}
    ref = sparse_variance_reference(post.kernel, Z, X, Xq, noise_var)
    err, thread_diff = {}, {}
    for name in ("factored", "single"):
        v1, v2 = forms[1][name][1], forms[2][name][1]
        err[name] = float(np.median(np.abs(v1 - ref) / ref))
        thread_diff[name] = float(np.max(np.abs(v2 - v1) / ref))
    post, old = forms[2]["factored"][0], forms[2]["single"][0]
    times = {"factored": [], "single": []}
    for _ in range(reps):  # interleaved, so load from other processes hits both
        for name, p in (("factored", post), ("single", old)):
            t0 = time.perf_counter()
            p.predict(Xq)
            times[name].append(time.perf_counter() - t0)
    ms = {k: 1e3 * C.median(v) for k, v in times.items()}
    print(f"M={m}, {n_query} queries, D={C.D}, reference latent variance median {np.median(ref):.3e} "
          f"(k(x,x) median {np.median(post.kernel.diag(Xq)):.3f}); build {build_s:.2f} s; {C.env_note()}")
    for name in ("factored", "single"):
        print(f"  {name:8s}: median rel. error {err[name]:.2e}, 1 vs 2 threads max change {thread_diff[name]:.2e}, "
              f"predict {ms[name]:.1f} ms")
    C.result(product=ms["factored"], baseline=ms["single"], baseline_what="single-matrix-kTAk-same-posterior",
             unit="ms", ratio=C.median_ratio(times["factored"], times["single"]),
             product_rel_err=err["factored"], baseline_rel_err=err["single"],
             product_thread_change=thread_diff["factored"], baseline_thread_change=thread_diff["single"],
             m=m, queries=n_query, blas_threads=C.blas_threads())


if __name__ == "__main__":
    main()
