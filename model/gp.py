"""GP posteriors for prediction, eqs. (8)-(9): exact and sparse (inducing points), on standardised data.

The hyperparameters come from ML-II (``model.ml2``, eq. 13); a posterior holds the arrays that
prediction needs (means, variances, their gradients for the linearised propagation and the local
model of the Monte Carlo free run). Both meet the ``posterior.Posterior`` contract, which is all the
free runs and their local model (``freerun.mc_local``) read.
"""
from __future__ import annotations

import numpy as np
from scipy import linalg

from .kernels import Kernel
from .linalg import chol_inverse, cholesky_jitter, lower_times_rows


class _Posterior:
    """What the exact and sparse posteriors share (``posterior.Posterior``): K(Xs, points) through one Gram
    product, eq. 8's constant shift, and the mean, variance and mean gradient at one or many points.
    A subclass provides ``points``, ``mean_weights``, ``reduction_rows`` and ``_reduction_one``."""

    def __init__(self, kernel: Kernel, noise_var: float, points: np.ndarray, weights: np.ndarray):
        self.kernel = kernel
        self.noise_var = float(noise_var)
        self._sq_points = np.einsum("ij,ij->i", points, points)
        # kernel may be a capped copy (Kernel.for_posterior): K_full = K + shift, so the mean of
        # eq. 8 is K w + shift * sum(w) while the variance uses the capped kernel
        self.mean_shift = float(kernel.cap_shift()) * float(np.sum(weights))

    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    def cross(self, Xs: np.ndarray) -> np.ndarray:
        """K(Xs, points) with one Gram product shared by all kernel parts."""
        return self.kernel.from_gram(Xs @ self.points.T, np.einsum("ij,ij->i", Xs, Xs), self._sq_points)

    def mean_grad(self, xs: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Mean, latent variance and d mean / d xs at one point xs (D,)."""
        k = self.cross(xs[None, :])
        w = self.mean_weights
        mean = float(k[0] @ w) + self.mean_shift
        var = max(float(self.kernel.diag(xs[None, :])[0] - self._reduction_one(k)), 1e-300)
        grad = self.kernel.grad_x(xs, self.points).T @ w
        return mean, var, grad

    def mean_var_grad(self, Xs: np.ndarray, block: int = 256, stride: int = 1):
        """``mean_grad`` for many points at once: mean (eq. 8), latent variance (eq. 9, as ``predict``)
        and d mean / d xs for every row of Xs, (rows,), (rows,), (rows, D); one kernel block per row block
        sharing one Gram product with the mean's gradient (``LinearisableKernel.value_and_grad_dot``).
        ``stride`` s > 1: eq. 9 only at the rows ``stride_rows(rows, s)`` (every s-th and the last), linearly
        interpolated between (``interpolate_rows``); mean and gradient at every row."""
        Xs = np.ascontiguousarray(Xs, dtype=float)
        n = Xs.shape[0]
        mean, var = np.empty(n), np.empty(n)
        grad = np.empty(Xs.shape)
        X, w = self.points, self.mean_weights
        sqX = np.einsum("ij,ij->i", X, X)
        keep = None if stride <= 1 else stride_rows(n, stride)
        for r0 in range(0, n, block):
            r1 = min(n, r0 + block)
            xb = Xs[r0:r1]
            Ks, grad[r0:r1] = self.kernel.value_and_grad_dot(xb, X, w, xb @ X.T, np.einsum("ij,ij->i", xb, xb),
                                                              sqX)
            np.dot(Ks, w, out=mean[r0:r1])
            mean[r0:r1] += self.mean_shift
            if keep is None:
                var[r0:r1] = self.kernel.diag(xb) - self.reduction_rows(Ks)
            else:
                sel = keep[(keep >= r0) & (keep < r1)] - r0
                if sel.size:
                    var[sel + r0] = self.kernel.diag(xb[sel]) - self.reduction_rows(Ks[sel])
        if keep is not None:
            var[:] = interpolate_rows(var[keep], keep, n)
        np.maximum(var, 1e-300, out=var)
        return mean, var, grad


def stride_rows(n: int, stride: int) -> np.ndarray:
    """The rows of n at which a strided eq. 9 is evaluated: every ``stride``-th from the first, and the last."""
    rows = np.arange(0, n, max(int(stride), 1))
    return rows if not n or rows[-1] == n - 1 else np.append(rows, n - 1)


def interpolate_rows(values: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    """Values at ``rows`` (``stride_rows``) linearly interpolated to all n rows."""
    return np.interp(np.arange(n, dtype=float), rows.astype(float), values)


class ExactPosterior(_Posterior):
    """Full GP posterior, eqs. (8)-(9), on standardised data.

    Stores the training rows ``X_train``, alpha = (K + sigma_y^2 I)^-1 y and Linv = L^-1 (lower), so
    that for test points Xs: mean = K(Xs, X_train) alpha (eq. 8) and
    var_f = k(Xs, Xs) - |Linv K(X_train, Xs)|^2 (eq. 9).
    """

    kind = "exact"

    def __init__(self, kernel: Kernel, noise_var: float, X: np.ndarray, alpha: np.ndarray, Linv: np.ndarray):
        self.X_train = X
        self.alpha = alpha
        self.Linv = np.ascontiguousarray(Linv)  # C order: Linv.T is its F-ordered (upper) view for BLAS
        self._LinvT32 = None
        super().__init__(kernel, noise_var, X, alpha)

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray,
            var_kernel: Kernel | None = None, backend: str = "numpy") -> "ExactPosterior":
        """alpha from ``kernel`` (eq. 8); Linv from ``var_kernel`` when given (its capped copy,
        ``Kernel.for_posterior``), which keeps eq. 9 exact when kernel carries a large constant.
        backend 'jax': the two solves on the JAX device (``ml2_jax.exact_solve_jax``)."""
        if backend == "jax":
            from .ml2_jax import exact_solve_jax as solve  # here: the optional backend stays out of numpy runs
        else:
            solve = cls._solve
        alpha, Linv = solve(kernel, noise_var, X, y)
        if var_kernel is None:
            return cls(kernel, noise_var, X, alpha, Linv)
        if var_kernel.cap_shift() > 0.0:
            Linv = solve(var_kernel, noise_var, X, y)[1]
        return cls(var_kernel, noise_var, X, alpha, Linv)

    @staticmethod
    def _solve(kernel, noise_var, X, y):
        K = kernel(X)
        K[np.diag_indices_from(K)] += noise_var
        L, _ = cholesky_jitter(K, overwrite=True)
        alpha = linalg.cho_solve((L, True), y, check_finite=False)
        Linv = linalg.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
        return alpha, np.tril(Linv)

    @property
    def points(self) -> np.ndarray:
        """The training rows (N, D) the posterior conditions on."""
        return self.X_train

    def predict(self, Xs: np.ndarray, return_var: bool = True, float32: bool = False):
        """Latent mean (eq. 8) and variance (eq. 9) at Xs (standardised units)."""
        Ks = self.cross(Xs)
        mean = Ks @ self.alpha
        mean += self.mean_shift
        if not return_var:
            return mean, None
        if float32:
            if self._LinvT32 is None:
                self._LinvT32 = np.ascontiguousarray(self.Linv, dtype=np.float32).T  # F-ordered Linv^T
            V = linalg.blas.strmm(1.0, self._LinvT32, Ks.astype(np.float32).T, side=0, lower=0, trans_a=1,
                                  overwrite_b=1).T
            red = np.einsum("ij,ij->i", V, V, dtype=np.float64)
        else:
            red = self.reduction_rows(Ks)
        var = self.kernel.diag(Xs) - red
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def reduction_rows(self, Ks: np.ndarray) -> np.ndarray:
        """|Linv k|^2 per row of Ks (eq. 9), float64; Ks is overwritten."""
        # a triangular product: dtrmm computes Linv Ks^T in P N^2 flops (half the dense Ks @ Linv.T),
        # without holding the GIL (``lower_times_rows``)
        V = lower_times_rows(self.Linv, Ks)
        return np.einsum("ij,ij->i", V, V)

    def _reduction_one(self, k: np.ndarray) -> float:
        v = self.Linv @ k[0]
        return float(v @ v)

    @property
    def mean_weights(self) -> np.ndarray:
        """w of the mean K(xs, X) w + mean_shift (eq. 8): alpha."""
        return self.alpha

    @property
    def variance_factor(self) -> np.ndarray:
        """F of eq. 9's variance k(x, x) - |F k|^2: Linv."""
        return self.Linv

    def arrays(self) -> dict:
        return {"X": self.X_train, "alpha": self.alpha, "Linv": self.Linv}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "ExactPosterior":
        return cls(kernel, noise_var, arrays["X"], arrays["alpha"], arrays["Linv"])


def kmm_cholesky(kernel: Kernel, Z: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of K(Z, Z) + 1e-8 mean(diag) I, the inducing-point Gram matrix as every
    sparse computation jitters it (``SparsePosterior``, ``sparse_variance_reference``)."""
    Kmm = kernel(Z)
    Kmm[np.diag_indices_from(Kmm)] += 1e-8 * np.mean(np.diag(Kmm))
    return cholesky_jitter(Kmm, overwrite=True)[0]


def sparse_variance_reference(kernel: Kernel, Z: np.ndarray, X: np.ndarray, Xs: np.ndarray,
                              noise_var: float) -> np.ndarray:
    """eq. 9's sparse latent variance at Xs by an independent route, for checks (slow: one QR of an
    (N + M) x M matrix per call): k(x,x) - |Lm^-1 k|^2 + |R^-T k|^2 with Sigma = R^T R from the QR
    factorisation of [Lm^T; Knm / sigma_y] (no Gram product, no explicit inverse), Kmm jittered by
    ``kmm_cholesky`` as in ``SparsePosterior``. X: the posterior's training rows; all inputs standardised."""
    Lm = kmm_cholesky(kernel, Z)
    R = np.linalg.qr(np.vstack([Lm.T, kernel.cross(X, Z) / np.sqrt(noise_var)]), mode="r")
    Kq = kernel.cross(Xs, Z).T
    t1 = linalg.solve_triangular(Lm, Kq, lower=True, check_finite=False)
    t2 = linalg.solve_triangular(R, Kq, trans="T", lower=False, check_finite=False)
    return kernel.diag(Xs) - np.sum(t1 ** 2, 0) + np.sum(t2 ** 2, 0)


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


class SparsePosterior(_Posterior):
    """Sparse (VFE / DTC predictive) posterior with M inducing inputs Z.

    With Kmm = K(Z, Z) = Lm Lm^T, Kmn = K(Z, X), Sigma = Kmm + sigma_y^-2 Kmn Knm:
    mean = K(Xs, Z) w, w = sigma_y^-2 Sigma^-1 Kmn y (eq. 8), and the latent variance (eq. 9)

        var_f = k(Xs, Xs) - k^T A k,   A = Kmm^-1 - Sigma^-1,   k = K(Z, Xs),

    evaluated as k(Xs, Xs) - |G k|^2 with the factor A = G^T G,
    G = diag(sqrt(s / (1 + s))) Q^T Lm^-1, where S = Q diag(s) Q^T is the eigendecomposition of
    sigma_y^-2 Lm^-1 Kmn Knm Lm^-T (so Kmm^-1 - Sigma^-1 = Lm^-T (I - (I + S)^-1) Lm^-1).
    Forming A itself is the same number in exact arithmetic, but when sigma_y^2 sits at ML-II's
    floor its entries reach 1/jitter while the variance is orders of magnitude smaller, so k^T A k
    carries rounding error larger than the variance and depends on the BLAS thread count. |G k|^2
    is a sum of squares of O(1) numbers, agrees with a QR evaluation of Sigma^-1
    (``sparse_variance_reference``), and costs the same one (rows x M x M) product as k^T A k
    (docs/numerics.md, safeguard 2). Bundles that store ``A`` itself still load (``legacy_A``; the
    loader warns).
    Building costs O(N M^2 + M^3).
    """

    kind = "sparse"

    def __init__(self, kernel: Kernel, noise_var: float, Z: np.ndarray, w: np.ndarray,
                 G: np.ndarray | None = None, legacy_A: np.ndarray | None = None):
        self.inducing = Z
        self.w = w
        if (G is None) == (legacy_A is None):
            raise ValueError("SparsePosterior needs the variance factor G (or legacy_A from an old bundle)")
        self.G = None if G is None else np.asarray(G, dtype=float)
        self.legacy_A = legacy_A
        # the right-hand operand of the per-block product: G^T (C order), or the legacy A
        self._right = np.ascontiguousarray(self.G.T) if G is not None else legacy_A
        self._right32 = None
        super().__init__(kernel, noise_var, Z, w)

    @property
    def A(self) -> np.ndarray:
        """Kmm^-1 - Sigma^-1 (for inspection; only legacy bundles predict with it)."""
        return self.legacy_A if self.legacy_A is not None else self.G.T @ self.G

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray, Z: np.ndarray,
            var_kernel: Kernel | None = None) -> "SparsePosterior":
        """w from ``kernel``; the variance factor G from ``var_kernel`` when given (see
        ``ExactPosterior.fit``). Each is computed once, from its own kernel."""
        Lm_inv, V, S = cls._whitened(kernel, noise_var, X, Z)
        LB, _ = cholesky_jitter(np.eye(Z.shape[0]) + S, overwrite=True)
        w = Lm_inv.T @ (chol_inverse(LB) @ (V @ y)) / noise_var
        if var_kernel is None:
            var_kernel = kernel
        elif var_kernel.cap_shift() > 0.0:
            Lm_inv, _, S = cls._whitened(var_kernel, noise_var, X, Z)
        s, Q = linalg.eigh(S, check_finite=False)
        s = np.maximum(s, 0.0)
        G = (np.sqrt(s / (1.0 + s))[:, None] * Q.T) @ np.tril(Lm_inv)
        return cls(var_kernel, noise_var, Z, w, G)

    @staticmethod
    def _whitened(kernel, noise_var, X, Z):
        """Lm^-1 (as LAPACK returns it), V = Lm^-1 Kmn (M x N) and S = sigma_y^-2 V V^T for one kernel."""
        m = Z.shape[0]
        Lm = kmm_cholesky(kernel, Z)
        V = linalg.solve_triangular(Lm, kernel.cross(Z, X), lower=True, check_finite=False)
        Lm_inv = linalg.solve_triangular(Lm, np.eye(m), lower=True, check_finite=False)
        return Lm_inv, V, (V @ V.T) / noise_var

    @property
    def points(self) -> np.ndarray:
        """The inducing inputs Z (M, D) the posterior conditions on."""
        return self.inducing

    ROW_BLOCK = 256  # test rows per block: the (rows x M) kernel block and its temporaries stay in cache

    def _reduction(self, Ks: np.ndarray, float32: bool) -> np.ndarray:
        """k^T A k per row of Ks (rows x M): |G k|^2, or k^T A k for a legacy bundle."""
        if float32:
            if self._right32 is None:
                self._right32 = self._right.astype(np.float32)
            K, R = Ks.astype(np.float32), self._right32
        else:
            K, R = Ks, self._right
        T = K @ R
        other = T if self.legacy_A is None else K
        return np.einsum("ij,ij->i", T, other, dtype=np.float64)

    def predict(self, Xs, return_var=True, float32=False):
        """Sparse predictive mean and latent variance at Xs (standardised units), in row blocks.

        Each block of ``ROW_BLOCK`` rows computes its kernel block K(Xs_b, Z) (one Gram product),
        mean K w and variance k(x, x) - |G k|^2, so the elementwise kernel work and the reduction
        run on cache-resident (rows x M) arrays instead of one (P x M) pass per operation.
        """
        Xs = np.asarray(Xs, dtype=float)
        P = Xs.shape[0]
        mean = np.empty(P)
        var = self.kernel.diag(Xs) if return_var else None
        sqs = np.einsum("ij,ij->i", Xs, Xs)
        step = self.ROW_BLOCK
        for r0 in range(0, P, step):
            r1 = min(P, r0 + step)
            Ks = self.kernel.from_gram(Xs[r0:r1] @ self.inducing.T, sqs[r0:r1], self._sq_points)
            np.dot(Ks, self.w, out=mean[r0:r1])
            mean[r0:r1] += self.mean_shift
            if return_var:
                var[r0:r1] -= self._reduction(Ks, float32)
        if not return_var:
            return mean, None
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def reduction_rows(self, Ks: np.ndarray) -> np.ndarray:
        """k^T A k per row of Ks (eq. 9), float64."""
        return self._reduction(Ks, False)

    def _reduction_one(self, k: np.ndarray) -> float:
        return self._reduction(k, False)[0]

    @property
    def mean_weights(self) -> np.ndarray:
        """w of the mean K(xs, Z) w + mean_shift (eq. 8)."""
        return self.w

    @property
    def variance_factor(self) -> np.ndarray | None:
        """F of eq. 9's variance k(x, x) - |F k|^2: G (None for a legacy bundle that stores only A)."""
        return self.G

    def arrays(self) -> dict:
        if self.legacy_A is not None:
            return {"Z": self.inducing, "w": self.w, "A": self.legacy_A}
        return {"Z": self.inducing, "w": self.w, "G": self.G}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "SparsePosterior":
        if "G" in arrays:
            return cls(kernel, noise_var, arrays["Z"], arrays["w"], G=arrays["G"])
        return cls(kernel, noise_var, arrays["Z"], arrays["w"], legacy_A=arrays["A"])
