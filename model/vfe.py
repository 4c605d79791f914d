"""Sparse ML-II: the Titsias (2009) variational free energy (VFE) bound with analytic gradients.

With M inducing inputs Z (held fixed, e.g. by k-means) and Qnn = Knm Kmm^-1 Kmn, the bound on
the log marginal likelihood of eq. (13) is

    F = log N(y | 0, Qnn + s2 I) - tr(Knn - Qnn) / (2 s2)                       (Titsias 2009)

It is maximised over the kernel log-parameters and log s2 (s2 = sigma_y^2, the noise variance)
at O(N M^2 + n_params N M) time and O(N M) memory per evaluation, instead of O(N^3) / O(N^2).
When Z = X the bound equals the exact log marginal likelihood (up to the O(N jitter / s2) effect of
the Kmm jitter; exactly with ``jitter=0``). A ``White`` part has zero cross-covariance K(Z, X), so it
only enters Kmm and diag Knn (there the Z = X identity does not hold).

Stable form (as in GPflow's SGPR): Lm = chol(Kmm + jitter), A = Lm^-1 Kmn / s, B = I + A A^T,
LB = chol(B), c = LB^-1 A y / s. Then

    -F = N/2 log 2pi + N/2 log s2 + sum log diag LB + y'y / (2 s2) - c'c / 2
         + (tr Knn / s2 - tr(A A^T)) / 2.

Gradient (derived by hand, matrix form). With w = LB^-T c and Binv = B^-1,

    d(-F) = tr(G_mm dKmm) + sum(G_mn * dKmn) + sum(d diag Knn) / (2 s2) + g_s2 d log s2,
    G_mm = 1/2 Lm^-T [(I - Binv) A A^T + w w^T] Lm^-1                          (M x M)
    G_mn = Lm^-T [((w w^T - (I - Binv)) A) / s - w y^T / s2]                   (M x N)
    g_s2 = 1/2 [N - (M - tr Binv) - y'y/s2 + 2 c'c - w' A A^T w - tr Knn/s2 + tr(A A^T)]

so each kernel parameter costs one O(N M) contraction with dKmn/dtheta_j (the kernel's own
``Kernel.iter_cross_grads``).
The Kmm jitter is relative to mean(diag Kmm), and its dependence on theta is differentiated too,
so the gradient is that of the objective actually evaluated.
"""
from __future__ import annotations

import time

import numpy as np
from scipy import linalg

from . import ml2
from .kernels import GradientKernel, Kernel, SparseBoundKernel, require
from .linalg import LOG_2PI, NotPositiveDefiniteError, chol_inverse, cholesky_jitter

DEFAULT_JITTER = 1e-8  # relative to mean(diag Kmm), as in SparsePosterior.fit
_JITTER_LADDER = (1e-10, 1e-8, 1e-6, 1e-4, 1e-2)


# --------------------------------------------------------------------------------------------
# Kernel gradients needed by the bound: cross-covariance K(Z, X) and diag K(X, X)
# --------------------------------------------------------------------------------------------
def cross_grads(kernel: Kernel, Z: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """K(Z, X) and [dK(Z, X)/dtheta_j] for each log-parameter (same order as ``kernel.theta``), from the
    kernel's own ``iter_cross_grads`` (Matern32, RBF, CubicPolynomial, White and Sums of them)."""
    G = Z @ X.T
    sq1 = np.einsum("ij,ij->i", Z, Z)
    sq2 = np.einsum("ij,ij->i", X, X)
    K = kernel.from_gram(G, sq1, sq2)
    return K, list(kernel.iter_cross_grads(G, sq1, sq2))


def diag_grads(kernel: Kernel, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """diag K(X, X) (N,) and [d diag/dtheta_j] for each log-parameter (``Kernel.diag_and_grads``)."""
    return kernel.diag_and_grads(X)


# --------------------------------------------------------------------------------------------
# Bound and gradient
# --------------------------------------------------------------------------------------------
def _chol_kmm(Kmm: np.ndarray, jitter: float) -> tuple[np.ndarray, float]:
    """Cholesky of Kmm + rel * mean(diag Kmm) I, escalating rel from ``jitter``. Returns (L, rel)."""
    m = Kmm.shape[0]
    scale = float(np.mean(np.diag(Kmm))) or 1.0
    ladder = [float(jitter)] + [j for j in _JITTER_LADDER if j > jitter]
    for rel in ladder:
        try:
            L = linalg.cholesky(Kmm + (rel * scale) * np.eye(m), lower=True, check_finite=False)
        except linalg.LinAlgError:
            continue
        if np.all(np.isfinite(L)):
            return L, rel
    raise NotPositiveDefiniteError(
        f"Kmm (M={m}) is not positive definite even with jitter {ladder[-1]:g} x mean diagonal; "
        "check for duplicated inducing inputs or extreme hyperparameters"
    )


def vfe_nlml_and_grad(
    theta: np.ndarray, kernel: Kernel, X: np.ndarray, y: np.ndarray, Z: np.ndarray,
    jitter: float = DEFAULT_JITTER,
) -> tuple[float, np.ndarray]:
    """Negative Titsias VFE bound (-F >= exact NLML) and its analytic gradient.

    theta = [kernel log-parameters..., log s2]; Z (M x D) fixed inducing inputs.
    Cost O(N M^2 + n_params N M); memory O(N M). Sets the kernel's theta as a side effect
    (like ``ml2.nlml_and_grad``). ``jitter`` is the starting relative jitter on Kmm.
    """
    theta = np.asarray(theta, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    kernel.set_theta(theta[:-1])
    s2 = float(np.exp(theta[-1]))
    s = np.sqrt(s2)
    n, m = X.shape[0], Z.shape[0]

    # --- forward -------------------------------------------------------------------------------
    Kmm, dKmm = kernel.K_and_grads(Z)
    Lm, rel = _chol_kmm(Kmm, jitter)
    Gram = Z @ X.T
    sqZ = np.einsum("ij,ij->i", Z, Z)
    sqX = np.einsum("ij,ij->i", X, X)
    Kmn = kernel.from_gram(Gram, sqZ, sqX)
    A = linalg.solve_triangular(Lm, Kmn, lower=True, check_finite=False)
    del Kmn
    A /= s                                                     # A = Lm^-1 Kmn / s   (M x N)
    AAT = A @ A.T
    B = AAT + np.eye(m)
    LB, _ = cholesky_jitter(B, overwrite=False)
    Ay = A @ y
    c = linalg.solve_triangular(LB, Ay, lower=True, check_finite=False) / s
    knn_diag, ddiag = diag_grads(kernel, X)
    tr_knn = float(np.sum(knn_diag))
    tr_aat = float(np.trace(AAT))
    yy = float(y @ y)
    cc = float(c @ c)
    neg_bound = (0.5 * n * (LOG_2PI + np.log(s2)) + float(np.sum(np.log(np.diag(LB))))
                 + 0.5 * yy / s2 - 0.5 * cc + 0.5 * (tr_knn / s2 - tr_aat))

    # --- reverse -------------------------------------------------------------------------------
    w = linalg.solve_triangular(LB, c, lower=True, trans="T", check_finite=False)   # LB^-T c
    Binv = chol_inverse(LB)
    IminusBinv = np.eye(m) - Binv                                # = Binv A A^T
    # G_mm = 1/2 Lm^-T [(I - Binv) A A^T + w w^T] Lm^-1
    Mid = IminusBinv @ AAT
    Mid += np.outer(w, w)
    Mid = 0.5 * (Mid + Mid.T)
    T = linalg.solve_triangular(Lm, Mid, lower=True, trans="T", check_finite=False)
    Gmm = 0.5 * linalg.solve_triangular(Lm, T.T, lower=True, trans="T", check_finite=False).T
    # G_mn = Lm^-T [((w w^T - (I - Binv)) A) / s - w y^T / s2]
    C = np.outer(w, w)
    C -= IminusBinv
    C /= s
    H = C @ A
    del A
    H -= np.outer(w / s2, y)
    Gmn = np.ascontiguousarray(linalg.solve_triangular(Lm, H, lower=True, trans="T", check_finite=False)).ravel()
    del H
    tr_gmm = float(np.trace(Gmm))
    Gmm = np.ascontiguousarray(Gmm).ravel()

    g = np.empty(theta.size)
    for j, (dmm, dmn) in enumerate(zip(dKmm, kernel.iter_cross_grads(Gram, sqZ, sqX))):
        g_mm = float(np.dot(Gmm, np.ascontiguousarray(dmm).ravel()))
        if rel:  # Kmm jitter rel * mean(diag Kmm) also moves with theta
            g_mm += rel * float(np.mean(np.diag(dmm))) * tr_gmm
        g[j] = g_mm + float(np.dot(Gmn, np.ascontiguousarray(dmn).ravel())) + 0.5 * float(np.sum(ddiag[j])) / s2
    wAAw = float(w @ (AAT @ w))
    g[-1] = 0.5 * (n - (m - float(np.trace(Binv))) - yy / s2 + 2.0 * cc - wAAw - tr_knn / s2 + tr_aat)
    return float(neg_bound), g


# --------------------------------------------------------------------------------------------
# Optimisation
# --------------------------------------------------------------------------------------------
def fit_vfe(
    kernel: Kernel,
    X: np.ndarray,
    y: np.ndarray,
    Z: np.ndarray,
    n_restarts: int = 0,
    seed: int = 0,
    theta0: np.ndarray | None = None,
    max_iter: int = 200,
    agree_tol: float = 0.5,
    warm_start_rows: int | None = 500,
) -> ml2.MLIIResult:
    """Sparse ML-II: minimise the negative VFE bound by L-BFGS-B with Z fixed.

    Same bounds, starting point (``ml2.initial_theta``), restart scheme and result type as
    ``ml2.fit_ml2``; ``MLIIResult.nlml`` holds the negative bound (an upper bound on the NLML).

    Starts: ``theta0`` if given; otherwise ``ml2.initial_theta`` and, when ``warm_start_rows``
    is set, also the exact ML-II optimum on that many evenly strided rows (O(rows^3), cheap).
    The second start matters on high-dimensional NARX regressors: from the data-scaled start
    the trace term tr(Knn - Qnn)/s2 is huge and L-BFGS-B can slide into the degenerate
    "everything is noise" optimum (s2 -> var(y)); the best final bound wins either way.
    Then ``n_restarts`` N(0, 1) log-space perturbations of the first start (stopping early
    once two runs agree within ``agree_tol`` nats). The kernel is left at the best
    hyperparameters.
    """
    for contract in (GradientKernel, SparseBoundKernel):
        require(kernel, contract, "the sparse bound (vfe.fit_vfe)")
    t0 = time.perf_counter()
    y = np.asarray(y, dtype=float).ravel()
    bounds = kernel.log_bounds() + [ml2.NOISE_LOG_BOUNDS]
    if theta0 is not None:
        starts = [np.asarray(theta0, float)]
    else:
        starts = [ml2.initial_theta(kernel, X, y)]
        if warm_start_rows:
            rows = np.unique(np.linspace(0, X.shape[0] - 1, min(int(warm_start_rows), X.shape[0])).astype(int))
            try:
                warm = ml2.fit_ml2(kernel.clone(), X[rows], y[rows], n_restarts=0, theta0=starts[0],
                                  max_iter=max_iter)
                starts.append(warm.theta)
            except NotPositiveDefiniteError:
                pass
    best, history, n_evals = ml2.multistart_lbfgsb(
        vfe_nlml_and_grad, (kernel, X, y, Z), starts, bounds, n_restarts=n_restarts, seed=seed,
        max_iter=max_iter, agree_tol=agree_tol)
    if best is None:
        raise NotPositiveDefiniteError("VFE ML-II failed from every start: Kmm/B never positive definite")
    kernel.set_theta(best.x[:-1])
    return ml2.MLIIResult(theta=best.x.copy(), nlml=float(best.fun), restarts=history,
                         seconds=time.perf_counter() - t0, n_evals=n_evals)


__all__ = ["cross_grads", "diag_grads", "fit_vfe", "vfe_nlml_and_grad"]
