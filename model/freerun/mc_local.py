"""The checked local model of the Monte Carlo free run (``mc.run_mc``): a second-order model of eq. 8 (mean)
and eq. 9 (latent variance) around the paths' mean regressor in its output-lag coordinates."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels import LocalKernel
from ..kernels.base import _r2_from_gram
from ..linalg import blas_threads, lower_times_rows_and_back
from ..posterior import Posterior


@dataclass(frozen=True, slots=True)
class LocalTerms:
    """``local_model``'s numbers around x (standardised units): mean(x + d) ~ m0 + gm . d + d^T Hm d / 2 and
    var(x + d) ~ v0 + gv . d + d^T Hv d / 2 for d zero beyond the ny output lags; ``mean_c``, ``var_c``: eq. 8-9
    exactly at the rows of Xc (None without Xc)."""

    m0: float
    gm: np.ndarray
    Hm: np.ndarray
    v0: float
    gv: np.ndarray
    Hv: np.ndarray
    mean_c: np.ndarray | None
    var_c: np.ndarray | None


def has_local_model(post) -> bool:
    """Whether ``local_model`` covers ``post``: a ``posterior.Posterior`` with a variance factor (not a
    legacy sparse bundle) whose kernel meets ``LocalKernel``."""
    return (isinstance(post, Posterior) and post.variance_factor is not None
            and post.kernel.supports(LocalKernel))


def local_model(post: Posterior, x: np.ndarray, ny: int, Xc: np.ndarray | None = None) -> LocalTerms:
    """Second-order model of the predictive mean (eq. 8) and latent variance (eq. 9) around one
    regressor x in its first ``ny`` coordinates (the lagged outputs).

    mean(x + d) ~ m0 + gm . d + d^T Hm d / 2 and var(x + d) ~ v0 + gv . d + d^T Hv d / 2 for d zero
    beyond ny. The variance is expanded as a whole, k(x, x) - |F k(x)|^2 with F the posterior's
    factor (G, or Linv for the exact posterior): q = |F k|^2 has gradient 2 (F J)^T F k and Hessian
    2 (F J)^T (F J) + 2 sum_n (F^T F k)_n d^2 k_n, J = d k / d x[:ny] (``LocalKernel.local_terms``).
    Costs O(M^2 ny) for one point (no per-path work). With ``Xc`` (rows x D), also eq. 8-9 exactly
    at those rows, sharing the one product with F.
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
    return LocalTerms(m0, gm, Hm, v0, gv, Hv, mean_c, var_c)


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
        self.fused = bool(getattr(self.kernel, "has_local_profile", False))  # declared by the kernel (LocalKernel)

    def __call__(self, x: np.ndarray, Xc: np.ndarray):
        ny, H = self.ny, self.H
        t = self._terms(x, Xc) if self.fused else local_model(self.post, x, ny, Xc)
        a = ny + 1
        np.multiply(t.Hm, 0.5, out=H[:ny, :ny])
        np.multiply(t.Hv, 0.5, out=H[:ny, a: a + ny])
        H[:ny, ny] = H[ny, :ny] = 0.5 * t.gm
        H[:ny, a + ny] = H[ny, a: a + ny] = 0.5 * t.gv
        H[ny, ny] = t.m0
        H[ny, a + ny] = t.v0
        return H, t.mean_c, t.var_c

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
        # the triangular product runs on scipy's BLAS, the rest of the step on numpy's; with more than one BLAS
        # thread their two thread pools would take the cores from each other, so there numpy's dense product
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
        return LocalTerms(m0, mw[1: 1 + ny], Hb[:, :ny], v0, gv, Hv, mean_c, var_c)
