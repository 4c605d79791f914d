"""GP posteriors for prediction, eqs. (8)-(9): exact and sparse (inducing points), on standardised data.

The hyperparameters come from ML-II (``model.ml2``, eq. 13); a posterior holds the arrays that
prediction needs (means, variances, their gradients for the linearised propagation and the local
model of the Monte Carlo free run). Both meet the ``posterior.Posterior`` contract, which is all the
free runs and ``local_model`` read.
"""
from __future__ import annotations

import os

import numpy as np
from scipy import linalg

from .kernels import Kernel, LocalKernel
from .kernels.base import _r2_from_gram
from .linalg import chol_inverse, cholesky_jitter
from .posterior import Posterior


def _fortran_dtrmm():
    """LAPACK's dtrmm as scipy's Cython BLAS exports it, called through ctypes (which releases the GIL
    for the call), or None where that export is missing. ``scipy.linalg.blas.dtrmm`` holds the GIL for
    the whole product, so a free run's worker thread (``freerun.simulate_linear``) would stall the
    Python loop running beside it; the arithmetic is the same routine's."""
    try:
        import ctypes

        from scipy.linalg import cython_blas

        cap = cython_blas.__pyx_capi__["dtrmm"]
        api = ctypes.pythonapi
        api.PyCapsule_GetName.restype = ctypes.c_char_p
        api.PyCapsule_GetName.argtypes = [ctypes.py_object]
        api.PyCapsule_GetPointer.restype = ctypes.c_void_p
        api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        ptr = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
        c, i = ctypes.c_char_p, ctypes.POINTER(ctypes.c_int)
        d, v = ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
        return ctypes.CFUNCTYPE(None, c, c, c, c, i, i, d, v, i, v, i)(ptr)
    except Exception:  # pragma: no cover - a scipy without the export: scipy.linalg.blas below
        return None


_DTRMM = _fortran_dtrmm()


_HELPER = []  # one lazily started helper thread for ``lower_times_rows(..., split=True)``


def two_cpus() -> bool:
    """Whether this process may run on two or more CPUs (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0)) >= 2
    except AttributeError:  # pragma: no cover - no sched_getaffinity (macOS, Windows)
        return (os.cpu_count() or 1) >= 2


_BLAS_LIBS = []  # threadpoolctl's controllers of the loaded BLAS libraries (numpy's and scipy's; found once)


def blas_threads() -> int:
    """The most threads any loaded BLAS (numpy's, scipy's) uses now; 1 where threadpoolctl finds none. The
    libraries are looked up once; each call asks their current thread count (so
    ``threadpoolctl.threadpool_limits`` blocks take effect)."""
    if not _BLAS_LIBS:
        try:
            from threadpoolctl import ThreadpoolController

            _BLAS_LIBS.append(ThreadpoolController().select(user_api="blas").lib_controllers)
        except Exception:  # pragma: no cover - threadpoolctl comes with scikit-learn
            _BLAS_LIBS.append([])
    counts = [int(c.num_threads) for c in _BLAS_LIBS[0]]
    return max(counts) if counts else 1


def lower_times_rows(L: np.ndarray, Ks: np.ndarray, split: bool = False, transpose: bool = False) -> np.ndarray:
    """(L Ks^T)^T for a lower-triangular C-ordered L (N, N) and rows Ks (rows, N), float64: row j is
    L k_j (``transpose``: L^T k_j). BLAS dtrmm (P N^2 flops, half a dense product) on a C-ordered copy of
    Ks, without the GIL where scipy exports it (``_fortran_dtrmm``), so other Python threads keep running.
    ``split``: where the process may use two CPUs and the BLAS runs on one thread, the first half of the rows
    on a helper thread while this thread does the second (with a multi-threaded BLAS, one call: two calls at
    once on its shared thread pool run several times slower than either alone)."""
    L = np.ascontiguousarray(L, dtype=np.float64)
    B = np.array(Ks, dtype=np.float64, order="C", copy=True)  # C (rows, N) = Fortran (N, rows): B^T
    rows, N = B.shape
    if _DTRMM is None or rows == 0 or N == 0:
        return linalg.blas.dtrmm(1.0, L.T, B.T, side=0, lower=0, trans_a=0 if transpose else 1, overwrite_b=1).T
    if split and rows >= 8 and _two_threads():
        h = rows // 2
        first = _helper().submit(_dtrmm_rows, L, B[:h], transpose)
        _dtrmm_rows(L, B[h:], transpose)
        first.result()
    else:
        _dtrmm_rows(L, B, transpose)
    return B


def lower_times_rows_and_back(L: np.ndarray, Ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``lower_times_rows(L, Ks)`` and L^T (L k_0) for its first row k_0, float64 (the local model's F [k | ...]
    and F^T F k). A product with one vector streams all of L for a few flops, so where the process may use
    two CPUs and the BLAS runs on one thread, the helper thread takes row 0, then L^T of it, then a share of
    the other rows that evens the two threads' work (one row alone costs about as much as a dozen in one
    call), while this thread does the rest; otherwise one call, then the second product."""
    L = np.ascontiguousarray(L, dtype=np.float64)
    B = np.array(Ks, dtype=np.float64, order="C", copy=True)
    rows, N = B.shape
    back = np.empty((1, N))
    if _DTRMM is None or rows == 0 or N == 0:
        B = lower_times_rows(L, B)
        return B, lower_times_rows(L, B[:1], transpose=True)[0]
    if rows < 8 or not _two_threads():
        _dtrmm_rows(L, B)
        back[0] = B[0]
        _dtrmm_rows(L, back, transpose=True)
        return B, back[0]
    extra = max(0, (rows - 13) // 2)  # the helper's share of the other rows: 8 of 28

    def first():
        _dtrmm_rows(L, B[:1])
        back[0] = B[0]
        _dtrmm_rows(L, back, transpose=True)
        if extra:
            _dtrmm_rows(L, B[1: 1 + extra])

    job = _helper().submit(first)
    _dtrmm_rows(L, B[1 + extra:])
    job.result()
    return B, back[0]


def _two_threads() -> bool:
    """Whether a product may be split over this thread and the helper: two CPUs, one BLAS thread (with more,
    two calls at once on the BLAS's shared thread pool run several times slower than either alone)."""
    return two_cpus() and blas_threads() == 1


def _helper():
    """The one helper thread of the split products (started on first use)."""
    if not _HELPER:
        from concurrent.futures import ThreadPoolExecutor

        _HELPER.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="gpnarx-trmm"))
    return _HELPER[0]


def _dtrmm_rows(L: np.ndarray, B: np.ndarray, transpose: bool = False) -> None:
    """B[j] := L B[j] (``transpose``: L^T B[j]) for every row of the C-ordered block B (rows, N)."""
    import ctypes

    rows, N = B.shape
    n, m, one = ctypes.c_int(N), ctypes.c_int(rows), ctypes.c_double(1.0)
    # Fortran view: A = C-ordered L read column-major = L^T (upper); B^T := op(A) B^T with op(A) = A^T = L
    # (or op(A) = A = L^T)
    _DTRMM(b"L", b"U", b"N" if transpose else b"T", b"N", ctypes.byref(n), ctypes.byref(m), ctypes.byref(one),
           L.ctypes.data, ctypes.byref(n), B.ctypes.data, ctypes.byref(n))


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

    def mean_var_grad(self, Xs: np.ndarray, block: int = 256):
        """``mean_grad`` for many points at once: mean (eq. 8), latent variance (eq. 9, as ``predict``)
        and d mean / d xs for every row of Xs, (rows,), (rows,), (rows, D); one kernel block per row block
        sharing one Gram product with the mean's gradient (``LinearisableKernel.value_and_grad_dot``)."""
        Xs = np.ascontiguousarray(Xs, dtype=float)
        n = Xs.shape[0]
        mean, var = np.empty(n), np.empty(n)
        grad = np.empty(Xs.shape)
        X, w = self.points, self.mean_weights
        sqX = np.einsum("ij,ij->i", X, X)
        for r0 in range(0, n, block):
            r1 = min(n, r0 + block)
            xb = Xs[r0:r1]
            Ks, grad[r0:r1] = self.kernel.value_and_grad_dot(xb, X, w, xb @ X.T, np.einsum("ij,ij->i", xb, xb),
                                                              sqX)
            np.dot(Ks, w, out=mean[r0:r1])
            mean[r0:r1] += self.mean_shift
            var[r0:r1] = self.kernel.diag(xb) - self.reduction_rows(Ks)
        np.maximum(var, 1e-300, out=var)
        return mean, var, grad


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


def has_local_model(post) -> bool:
    """Whether ``local_model`` covers ``post``: a ``posterior.Posterior`` with a variance factor (not a
    legacy sparse bundle) whose kernel meets ``LocalKernel``."""
    return (isinstance(post, Posterior) and post.variance_factor is not None
            and post.kernel.supports(LocalKernel))


def local_model(post: Posterior, x: np.ndarray, ny: int, Xc: np.ndarray | None = None):
    """Second-order model of the predictive mean (eq. 8) and latent variance (eq. 9) around one
    regressor x in its first ``ny`` coordinates (the lagged outputs).

    mean(x + d) ~ m0 + gm . d + d^T Hm d / 2 and var(x + d) ~ v0 + gv . d + d^T Hv d / 2 for d zero
    beyond ny. The variance is expanded as a whole, k(x, x) - |F k(x)|^2 with F the posterior's
    factor (G, or Linv for the exact posterior): q = |F k|^2 has gradient 2 (F J)^T F k and Hessian
    2 (F J)^T (F J) + 2 sum_n (F^T F k)_n d^2 k_n, J = d k / d x[:ny] (``LocalKernel.local_terms``).
    Costs O(M^2 ny) for one point (no per-path work). With ``Xc`` (rows x D), also eq. 8-9 exactly
    at those rows, sharing the one product with F. Returns (m0, gm, Hm, v0, gv, Hv, mean_c, var_c).
    Called once per Monte Carlo step, so the contract is checked once per run by the caller
    (``has_local_model``: a kernel that meets ``LocalKernel``, not a legacy sparse bundle).
    """
    F = post.variance_factor
    if F is None:
        raise NotImplementedError("legacy sparse bundle (no variance factor G)")
    k, J, hess = post.kernel.local_terms(x, post.points, ny)
    kxx, gk, Hk = post.kernel.diag_local(x, ny)
    w = post.mean_weights
    nc = 0 if Xc is None else Xc.shape[0]
    B = np.empty((k.size, 1 + ny + nc))
    B[:, 0] = k
    B[:, 1: 1 + ny] = J
    if nc:
        B[:, 1 + ny:] = post.cross(Xc).T
    mw = w @ B  # k.w, J^T w, Kc w
    FB = F @ B
    Fk, FJ = FB[:, 0], FB[:, 1: 1 + ny]
    m0 = float(mw[0]) + post.mean_shift
    gm = mw[1: 1 + ny]
    Hm = hess(w)
    v0 = kxx - float(Fk @ Fk)
    gv = gk - 2.0 * (FJ.T @ Fk)
    Hv = Hk - 2.0 * (FJ.T @ FJ) - 2.0 * hess(F.T @ Fk)
    mean_c = var_c = None
    if nc:
        mean_c = mw[1 + ny:] + post.mean_shift
        FK = FB[:, 1 + ny:]
        var_c = np.maximum(post.kernel.diag(Xc) - np.einsum("ij,ij->j", FK, FK), 1e-300)
    return m0, gm, Hm, v0, gv, Hv, mean_c, var_c


class LocalModel:
    """``local_model`` for the many steps of one Monte Carlo run, as one augmented quadratic form per quantity.

    ``model(x, Xc)`` returns (H, mean_c, var_c): H (ny + 1, 2 (ny + 1)) holds [Hm_aug | Hv_aug] with
    Hm_aug = [[Hm / 2, gm / 2], [gm^T / 2, m0]] (likewise for the variance), so that with
    d_aug = [d, 1] the model's mean at x + d is d_aug^T Hm_aug d_aug and its latent variance
    d_aug^T Hv_aug d_aug: every path's pair from one (P x (ny + 1)) product and two row sums. mean_c and
    var_c are eq. 8-9 at the rows of Xc, as ``local_model``. The numbers are ``local_model``'s to
    round-off; the per-run constants ([F; w^T], the output-lag columns of the points) are kept, and a
    kernel with a ``LocalProfile`` (``LocalKernel.local_profile``) gives k, J and both Hessians (mean
    weights w and F^T F k) with a few products on its coefficient vectors: one [F; w^T] [k | J | Kc]
    product, one Gram of F [k | J], one F^T (F k) and one Hessian product per coefficient kind.
    Other kernels take ``local_model`` itself.
    """

    def __init__(self, post: Posterior, ny: int):
        F = post.variance_factor
        if F is None:
            raise NotImplementedError("legacy sparse bundle (no variance factor G)")
        self.post, self.kernel, self.ny = post, post.kernel, int(ny)
        self.Z = np.ascontiguousarray(post.points, dtype=float)
        self.Zy = np.ascontiguousarray(self.Z[:, :ny])
        self.sqZ = np.einsum("ij,ij->i", self.Z, self.Z)
        w = np.asarray(post.mean_weights, dtype=float)
        self.FW = np.vstack([F, w[None, :]])  # one product gives F B and w^T B
        self.FT = self.FW[:-1].T
        # a lower-triangular F (the exact posterior's Linv): F B by dtrmm (half the flops), w^T B apart
        self.F_lower = (F.shape[0] == F.shape[1] and not np.any(np.triu(F, 1)))
        self.F = np.ascontiguousarray(F, dtype=float) if self.F_lower else None
        self.w = w
        self.shift = float(post.mean_shift)
        M, D = self.Z.shape
        self.D = np.empty((M, D))
        self.beta = np.empty((M, 2))  # the two Hessians' weights: w (mean) and F^T F k (variance)
        self.beta[:, 0] = w
        self.H = np.zeros((ny + 1, 2 * (ny + 1)))
        self.diag = np.arange(ny)
        self.C = np.empty((2 * M, ny))
        self.C[M:] = self.Zy
        self.Wt = np.empty((2 * M, 2))
        self.U = np.empty((2 * M, 2, ny))
        self.fused = self.kernel.local_profile(np.ones((1, 1)), np.ones((1, 1)), np.ones(1)) is not None

    def __call__(self, x: np.ndarray, Xc: np.ndarray):
        ny, H = self.ny, self.H
        if not self.fused:
            m0, gm, Hm, v0, gv, Hv, mean_c, var_c = local_model(self.post, x, ny, Xc)
        else:
            m0, gm, Hm, v0, gv, Hv, mean_c, var_c = self._terms(x, Xc)
        a = ny + 1
        np.multiply(Hm, 0.5, out=H[:ny, :ny])
        np.multiply(Hv, 0.5, out=H[:ny, a: a + ny])
        H[:ny, ny] = H[ny, :ny] = 0.5 * gm
        H[:ny, a + ny] = H[ny, a: a + ny] = 0.5 * gv
        H[ny, ny] = m0
        H[ny, a + ny] = v0
        return H, mean_c, var_c

    def _terms(self, x, Xc):
        ny, Z, Zy, kern = self.ny, self.Z, self.Zy, self.kernel
        M = Z.shape[0]
        nc = Xc.shape[0]
        Xa = np.empty((1 + nc, Z.shape[1]))  # x and the rows of Xc: one Gram product, one profile
        Xa[0] = x
        Xa[1:] = Xc
        G = Xa @ Z.T
        sqa = np.einsum("ij,ij->i", Xa, Xa)
        prof = kern.local_profile(_r2_from_gram(G, sqa, self.sqZ), G, sqa)
        C = self.C  # [x - Z | Z] in the output lags, stacked (2M, ny)
        Dy = np.subtract(x[:ny], Zy, out=C[:M])
        B = np.empty((M, 1 + ny + nc))  # [k | J | K(Z, Xc)]
        B[:, 0] = prof.k[0]
        J = B[:, 1: 1 + ny]
        if prof.a is not None:
            np.multiply(Dy, prof.a[:, None], out=J)
            if prof.b is not None:
                J += prof.b[:, None] * Zy
        elif prof.b is not None:
            np.multiply(Zy, prof.b[:, None], out=J)
        else:
            J[:] = 0.0
        B[:, 1 + ny:] = prof.k[1:].T
        # the triangular product runs on scipy's BLAS, the rest of the step on numpy's: with more than one BLAS
        # thread the two libraries' thread pools take the cores from each other, so then numpy's dense product
        tri = self.F_lower and blas_threads() == 1
        if tri:
            FBt, Fback = lower_times_rows_and_back(self.F, B.T)  # F [k | J | Kc] and F^T F k
            FB = FBt.T
            mw = self.w @ B
        else:
            FWB = self.FW @ B
            mw = FWB[M]
            FB = FWB[:M]
        FkJ = FB[:, : 1 + ny]
        Gr = FkJ.T @ FkJ  # [Fk | FJ]^T [Fk | FJ]
        beta = self.beta
        if tri:
            beta[:, 1] = Fback
        else:
            beta[:, 1] = self.FT @ FB[:, 0]
        # [hess(w) | hess(F^T F k)] = C^T diag(weights) C for both weights in one product, + the q terms
        Wt = self.Wt
        for half, coef in ((Wt[:M], prof.p), (Wt[M:], prof.t)):
            if coef is None:
                half[:] = 0.0
            else:
                np.multiply(beta, coef[:, None], out=half)
        U = np.multiply(C[:, None, :], Wt[:, :, None], out=self.U)
        Hb = C.T @ U.reshape(2 * M, 2 * ny)
        di = self.diag
        if prof.q is not None:
            bq = prof.q @ beta
            Hb[di, di] += bq[0]
            Hb[di, di + ny] += bq[1]
        xy = x[:ny]
        m0 = float(mw[0]) + self.shift
        v0 = float(prof.kd[0]) - float(Gr[0, 0])
        gv = prof.dg * xy
        gv -= 2.0 * Gr[1:, 0]
        Hv = np.multiply.outer(xy, prof.dH * xy)
        Hv[di, di] += prof.dI
        Hv -= 2.0 * Gr[1:, 1:]
        Hv -= 2.0 * Hb[:, ny:]
        mean_c = mw[1 + ny:] + self.shift
        FK = FB[:, 1 + ny:]
        var_c = np.maximum(prof.kd[1:] - np.einsum("ij,ij->j", FK, FK), 1e-300)
        return m0, mw[1: 1 + ny], Hb[:, :ny], v0, gv, Hv, mean_c, var_c


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
