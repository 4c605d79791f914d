"""GP regression: ML-II hyperparameters (eq. 13) and posteriors for prediction (eqs. 8-9).

The model (kernel + Gaussian likelihood of eq. 2) is kept separate from inference: ``fit_ml2``
finds hyperparameters; ``ExactPosterior`` and ``SparsePosterior`` turn them and the training data
into the arrays needed to predict. Everything works on standardised regressors and targets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg
from scipy.optimize import minimize

from .kernels import Kernel

LOG_2PI = np.log(2.0 * np.pi)
NOISE_LOG_BOUNDS = (np.log(1e-8), np.log(10.0))
JITTERS = (0.0, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2)


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """K + sigma_y^2 I stayed non positive definite after jitter escalation."""


def cholesky_jitter(K: np.ndarray, overwrite: bool = False) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of K, adding jitter (relative to mean diag) until it succeeds.

    Returns (L, jitter added). Raises NotPositiveDefiniteError naming the largest jitter tried.
    """
    scale = float(np.mean(np.diag(K))) or 1.0
    for rel in JITTERS:
        try:
            if rel:
                Kj = K + (rel * scale) * np.eye(K.shape[0])
            else:
                Kj = K if not overwrite else K
            L = linalg.cholesky(Kj, lower=True, overwrite_a=overwrite and rel == 0.0, check_finite=False)
            if np.all(np.isfinite(L)):
                return L, rel * scale
        except linalg.LinAlgError:
            continue
    raise NotPositiveDefiniteError(
        f"covariance matrix (N={K.shape[0]}) is not positive definite even with jitter "
        f"{JITTERS[-1]:g} x mean diagonal; check for duplicated regressors or extreme hyperparameters"
    )


def chol_inverse(L: np.ndarray) -> np.ndarray:
    """(L L^T)^-1 from the lower Cholesky factor via LAPACK potri (symmetrised)."""
    inv, info = linalg.lapack.dpotri(L, lower=1)
    if info != 0:
        raise NotPositiveDefiniteError(f"potri failed (info={info})")
    inv = np.tril(inv)
    inv += np.tril(inv, -1).T
    return inv


def nlml_and_grad(theta: np.ndarray, kernel: Kernel, X: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood, eq. (13) negated, and its analytic gradient.

    theta = [kernel log-parameters..., log sigma_y^2]. One Cholesky of K + sigma_y^2 I.
    dNLML/dtheta_j = 0.5 tr((K^-1 - alpha alpha^T) dK/dtheta_j), alpha = K^-1 y.
    """
    kernel.set_theta(theta[:-1])
    noise = float(np.exp(theta[-1]))
    K, grads = kernel.K_and_grads(X)
    K[np.diag_indices_from(K)] += noise
    L, _ = cholesky_jitter(K, overwrite=True)
    alpha = linalg.cho_solve((L, True), y, check_finite=False)
    n = y.size
    nlml = 0.5 * float(y @ alpha) + float(np.sum(np.log(np.diag(L)))) + 0.5 * n * LOG_2PI
    W = chol_inverse(L)
    W -= np.outer(alpha, alpha)
    g = np.empty(theta.size)
    for j, dK in enumerate(grads):
        g[j] = 0.5 * float(np.einsum("ij,ij->", W, dK))
    g[-1] = 0.5 * noise * float(np.trace(W))
    return nlml, g


def initial_theta(kernel: Kernel, X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Starting log-hyperparameters from data scales (standardised data).

    Stationary parts get variance ~ var(y) and lengthscale ~ median pairwise distance; dot-product
    parts get a small variance and scale 1/D; the noise starts at 1% of var(y).
    """
    from .kernels import CubicPolynomial, Matern32, RBF, Sum, White

    rng = np.random.default_rng(0)
    sub = X[rng.choice(X.shape[0], size=min(500, X.shape[0]), replace=False)]
    d2 = np.sum((sub[:, None, :] - sub[None, :, :]) ** 2, axis=-1)
    med = float(np.sqrt(np.median(d2[d2 > 0]))) if np.any(d2 > 0) else 1.0
    vy = float(np.var(y)) or 1.0
    D = X.shape[1]
    parts = kernel.parts if isinstance(kernel, Sum) else [kernel]
    theta = []
    for p in parts:
        if isinstance(p, (Matern32, RBF)):
            theta += [np.log(vy), np.log(med)]
        elif isinstance(p, CubicPolynomial):
            theta += [np.log(0.1 * vy), np.log(1.0 / D), np.log(1.0)]
        elif isinstance(p, White):
            theta += [np.log(1e-3 * vy)]
        else:
            theta += list(p.theta)
    theta.append(np.log(1e-2 * vy))
    return np.array(theta, dtype=float)


@dataclass
class MLIIResult:
    theta: np.ndarray
    nlml: float
    restarts: list = field(default_factory=list)  # (nlml, n_iter) per start
    seconds: float = 0.0


def fit_ml2(
    kernel: Kernel,
    X: np.ndarray,
    y: np.ndarray,
    n_restarts: int = 2,
    seed: int = 0,
    max_iter: int = 200,
    agree_tol: float = 0.5,
    theta0: np.ndarray | None = None,
) -> MLIIResult:
    """ML-II: maximise eq. (13) by L-BFGS-B over log-hyperparameters, with seeded restarts.

    Start 0 is the data-scaled initial point; each restart perturbs it by N(0, 1) in log space.
    Restarts stop early once two starts agree within ``agree_tol`` nats (fewer restarts when
    they agree). The kernel is left at the best hyperparameters; returns the best theta
    (kernel log-parameters then log sigma_y^2) and its NLML.
    """
    t0 = time.perf_counter()
    base = initial_theta(kernel, X, y) if theta0 is None else np.asarray(theta0, float)
    bounds = kernel.log_bounds() + [NOISE_LOG_BOUNDS]
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    rng = np.random.default_rng(seed)
    best = None
    history = []
    for r in range(n_restarts + 1):
        start = base if r == 0 else np.clip(base + rng.normal(0.0, 1.0, base.size), lo, hi)
        try:
            res = minimize(
                nlml_and_grad, start, args=(kernel, X, y), jac=True, method="L-BFGS-B",
                bounds=bounds, options={"maxiter": max_iter},
            )
        except NotPositiveDefiniteError:
            history.append((float("inf"), 0))
            continue
        history.append((float(res.fun), int(res.nit)))
        if best is None or res.fun < best.fun:
            best = res
        finite = sorted(h[0] for h in history if np.isfinite(h[0]))
        if len(finite) >= 2 and finite[1] - finite[0] < agree_tol:
            break
    if best is None:
        raise NotPositiveDefiniteError("ML-II failed from every start: covariance never positive definite")
    kernel.set_theta(best.x[:-1])
    return MLIIResult(theta=best.x.copy(), nlml=float(best.fun), restarts=history, seconds=time.perf_counter() - t0)


class ExactPosterior:
    """Full GP posterior, eqs. (8)-(9), on standardised data.

    Stores alpha = (K + sigma_y^2 I)^-1 y and Linv = L^-1 (lower), so that for test points Xs:
    mean = K(Xs, X) alpha (eq. 8) and var_f = k(Xs, Xs) - |Linv K(X, Xs)|^2 (eq. 9).
    """

    kind = "exact"

    def __init__(self, kernel: Kernel, noise_var: float, X: np.ndarray, alpha: np.ndarray, Linv: np.ndarray):
        self.kernel = kernel
        self.noise_var = float(noise_var)
        self.X = X
        self.alpha = alpha
        self.Linv = Linv
        self._sqX = np.einsum("ij,ij->i", X, X)
        self._LinvT32 = None

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray) -> "ExactPosterior":
        K = kernel(X)
        K[np.diag_indices_from(K)] += noise_var
        L, _ = cholesky_jitter(K, overwrite=True)
        alpha = linalg.cho_solve((L, True), y, check_finite=False)
        Linv = linalg.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
        return cls(kernel, noise_var, X, alpha, np.tril(Linv))

    @property
    def n_points(self) -> int:
        return self.X.shape[0]

    def cross(self, Xs: np.ndarray) -> np.ndarray:
        """K(Xs, X) with one Gram product shared by all kernel parts."""
        return self.kernel.from_gram(Xs @ self.X.T, np.einsum("ij,ij->i", Xs, Xs), self._sqX)

    def predict(self, Xs: np.ndarray, return_var: bool = True, float32: bool = False):
        """Latent mean (eq. 8) and variance (eq. 9) at Xs (standardised units)."""
        Ks = self.cross(Xs)
        mean = Ks @ self.alpha
        if not return_var:
            return mean, None
        if float32:
            if self._LinvT32 is None:
                self._LinvT32 = np.ascontiguousarray(self.Linv.T, dtype=np.float32)
            V = Ks.astype(np.float32) @ self._LinvT32
            red = np.einsum("ij,ij->i", V, V, dtype=np.float64)
        else:
            V = Ks @ self.Linv.T
            red = np.einsum("ij,ij->i", V, V)
        var = self.kernel.diag(Xs) - red
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def mean_grad(self, xs: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Mean, latent variance and d mean / d xs at one point xs (D,)."""
        k = self.cross(xs[None, :])[0]
        mean = float(k @ self.alpha)
        v = self.Linv @ k
        var = max(float(self.kernel.diag(xs[None, :])[0] - v @ v), 1e-300)
        grad = self.kernel.grad_x(xs, self.X).T @ self.alpha
        return mean, var, grad

    def arrays(self) -> dict:
        return {"X": self.X, "alpha": self.alpha, "Linv": self.Linv}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "ExactPosterior":
        return cls(kernel, noise_var, arrays["X"], arrays["alpha"], arrays["Linv"])


def choose_inducing(X: np.ndarray, m: int, seed: int = 0) -> np.ndarray:
    """M inducing inputs by k-means (k-means++ start, seeded) on the standardised regressors."""
    from scipy.cluster.vq import kmeans2

    if X.shape[0] <= m:
        return X.copy()
    rng = np.random.default_rng(seed)
    Z, _ = kmeans2(X, m, minit="++", seed=rng, iter=20)
    # drop any duplicate / empty centres by falling back to data points
    Z = np.unique(Z, axis=0)
    if Z.shape[0] < m:
        extra = X[rng.choice(X.shape[0], m - Z.shape[0], replace=False)]
        Z = np.vstack([Z, extra])
    return Z


class SparsePosterior:
    """Sparse (VFE / DTC predictive) posterior with M inducing inputs Z.

    With Kmm = K(Z, Z), Kmn = K(Z, X), Sigma = Kmm + sigma_y^-2 Kmn Knm:
    mean = K(Xs, Z) w, w = sigma_y^-2 Sigma^-1 Kmn y, and
    var_f = k(Xs, Xs) - K(Xs, Z) A K(Z, Xs), A = Kmm^-1 - Sigma^-1.
    Building costs O(N M^2); each prediction O(M^2) per test point.
    """

    kind = "sparse"

    def __init__(self, kernel: Kernel, noise_var: float, Z: np.ndarray, w: np.ndarray, A: np.ndarray):
        self.kernel = kernel
        self.noise_var = float(noise_var)
        self.X = Z
        self.w = w
        self.A = A
        self._sqZ = np.einsum("ij,ij->i", Z, Z)
        self._A32 = None

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray, Z: np.ndarray) -> "SparsePosterior":
        m = Z.shape[0]
        Kmm = kernel(Z)
        Lm, _ = cholesky_jitter(Kmm + 1e-8 * np.mean(np.diag(Kmm)) * np.eye(m), overwrite=True)
        Kmn = kernel.cross(Z, X)
        V = linalg.solve_triangular(Lm, Kmn, lower=True, check_finite=False)  # M x N
        B = np.eye(m) + (V @ V.T) / noise_var
        LB, _ = cholesky_jitter(B, overwrite=True)
        Binv = chol_inverse(LB)
        Lm_inv = linalg.solve_triangular(Lm, np.eye(m), lower=True, check_finite=False)
        A = Lm_inv.T @ (np.eye(m) - Binv) @ Lm_inv
        A = 0.5 * (A + A.T)
        w = Lm_inv.T @ (Binv @ (V @ y)) / noise_var
        return cls(kernel, noise_var, Z, w, A)

    @property
    def n_points(self) -> int:
        return self.X.shape[0]

    def cross(self, Xs):
        return self.kernel.from_gram(Xs @ self.X.T, np.einsum("ij,ij->i", Xs, Xs), self._sqZ)

    def predict(self, Xs, return_var=True, float32=False):
        Ks = self.cross(Xs)
        mean = Ks @ self.w
        if not return_var:
            return mean, None
        if float32:
            if self._A32 is None:
                self._A32 = self.A.astype(np.float32)
            Ks32 = Ks.astype(np.float32)
            red = np.einsum("ij,ij->i", Ks32 @ self._A32, Ks32, dtype=np.float64)
        else:
            red = np.einsum("ij,ij->i", Ks @ self.A, Ks)
        var = self.kernel.diag(Xs) - red
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def mean_grad(self, xs):
        k = self.cross(xs[None, :])[0]
        mean = float(k @ self.w)
        var = max(float(self.kernel.diag(xs[None, :])[0] - k @ self.A @ k), 1e-300)
        grad = self.kernel.grad_x(xs, self.X).T @ self.w
        return mean, var, grad

    def arrays(self) -> dict:
        return {"Z": self.X, "w": self.w, "A": self.A}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "SparsePosterior":
        return cls(kernel, noise_var, arrays["Z"], arrays["w"], arrays["A"])
