"""The cubic polynomial kernel of eq. (11), with the optional cap on its constant term."""
from __future__ import annotations

import numpy as np

from .base import CONTRACTS, Kernel, LocalProfile, MeanTerms

DEFAULT_CONSTANT_CAP = 1.0  # variance of the standardised output; GPNARX(constant_cap=...) default


def check_constant_cap(cap, name: str = "constant_cap") -> float | None:
    """``cap`` as a float (or None); anything else that is not a finite positive number is refused."""
    if cap is not None and (isinstance(cap, bool) or not isinstance(cap, (int, float, np.floating))
                            or not np.isfinite(cap) or cap <= 0):
        raise ValueError(f"{name} must be a positive number or None, got {cap!r}")
    return None if cap is None else float(cap)


class CubicPolynomial(Kernel, *CONTRACTS):  # meets every contract of kernels.base
    """Cubic polynomial kernel, eq. (11): sigma_p^2 (s x.x' + b)^3.

    Expanded, sigma_p^2 (t + b)^3 = sigma_p^2 [t (3 b^2 + 3 b t + t^2)] + sigma_p^2 b^3 with
    t = s x.x': a constant term sigma_p^2 b^3 (the prior variance of a constant offset) plus terms
    that vanish at x.x' = 0. ML-II (eq. 13) on standardised data often drives b up (the likelihood
    is flat in the offset's prior variance once it is broad), e.g. sigma_p^2 b^3 = 1.55e4 on the BERT
    stand-in against a latent variance near 1e-4: the predictive variance k(x,x) - k A k then cancels
    to below float64 precision. ``constant_cap`` (standardised output variance units; None = no cap)
    replaces the constant term by min(sigma_p^2 b^3, constant_cap) and evaluates the rest in the
    expanded form, without that cancellation. Posteriors take their variance from the capped kernel
    and their mean from the uncapped one (``gp.ExactPosterior`` / ``gp.SparsePosterior``: the two
    kernels differ by the constant ``cap_shift()``); ML-II uses the uncapped kernel, so the
    hyperparameters and the predicted means are eq. 13's and eq. 8's.
    """

    param_names = ("variance", "scale", "bias")

    def __init__(self, variance: float = 1.0, scale: float = 1.0, bias: float = 1.0,
                 constant_cap: float | None = None) -> None:
        self.theta = np.log([variance, scale, bias]).astype(float)
        self.constant_cap = None if constant_cap is None else float(constant_cap)

    def _capped(self, T: np.ndarray) -> np.ndarray:
        """sigma_p^2 [t (3b^2 + 3bt + t^2)] + min(sigma_p^2 b^3, cap) for t = T (modified in place)."""
        var, _, b = np.exp(self.theta)
        K = T * T
        K += (3.0 * b) * T
        K += 3.0 * b * b
        K *= T
        K *= var
        K += min(var * b**3, self.constant_cap)
        return K

    def __call__(self, X, X2=None):
        return self.from_gram(X @ (X if X2 is None else X2).T, None, None)  # a dot-product kernel: G is enough

    def K_and_grads(self, X):
        if self.constant_cap is not None:
            raise ValueError("a kernel with constant_cap is for posteriors; ML-II uses the uncapped kernel")
        var, s, b = np.exp(self.theta)
        D = X @ X.T
        G = s * D + b
        G2 = G * G
        K = var * G2 * G
        return K, [K.copy(), 3.0 * var * G2 * (s * D), 3.0 * var * G2 * b]

    def diag(self, X):
        var, s, b = np.exp(self.theta)
        if self.constant_cap is not None:
            return self._capped(s * np.einsum("ij,ij->i", X, X))
        return var * (s * np.einsum("ij,ij->i", X, X) + b) ** 3

    def from_gram(self, G, sq1, sq2):
        var, s, b = np.exp(self.theta)
        H = G * s
        if self.constant_cap is not None:
            return self._capped(H)
        H += b
        K = H * H
        K *= H
        K *= var
        return K

    def cap_shift(self) -> float:
        if self.constant_cap is None:
            return 0.0
        var, _, b = np.exp(self.theta)
        return max(float(var * b**3) - self.constant_cap, 0.0)

    def for_posterior(self, constant_cap: float | None = None) -> "CubicPolynomial":
        k = self.clone()
        k.constant_cap = None if constant_cap is None else float(constant_cap)
        return k

    def to_dict(self) -> dict:
        d = super().to_dict()
        if self.constant_cap is not None:
            d["constant_cap"] = self.constant_cap
        return d

    def grad_x(self, xs, X):
        var, s, b = np.exp(self.theta)
        G = s * (X @ xs) + b
        return (3.0 * var * s * G * G)[:, None] * X

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        # sum_n w_n 3 sigma_p^2 s (s xs.x_n + b)^2 x_n (the capped constant has no gradient)
        var, s, b = np.exp(self.theta)
        H = (Xs @ X.T if G is None else G) * s
        H += b
        H *= H
        H *= (3.0 * var * s) * w
        return H @ X

    def local_terms(self, x, X, ny):
        # h = s x.x_n + b (eq. 11): grad = 3 var s h^2 x_n, Hessian = 6 var s^2 h x_n x_n^T
        var, s, b = np.exp(self.theta)
        k = self.cross(x[None, :], X)[0]  # capped as in predictions
        h = s * (X @ x) + b
        Zy = X[:, :ny]
        J = (3.0 * var * s * h * h)[:, None] * Zy

        def hess(beta):
            return (6.0 * var * s * s) * (Zy.T @ ((beta * h)[:, None] * Zy))

        return k, J, hess

    def local_profile(self, r2, g, sq):
        # local_terms' coefficients: h = s g + b, b_n = 3 var s h^2, t_n = 6 var s^2 h; diag_local's
        # with t = s |x|^2: dg = dI = 6 var s (t + b)^2, dH = 24 var s^2 (t + b)
        var, s, b = np.exp(self.theta)
        k = self.from_gram(g, None, None)  # capped as in predictions
        kd = self._capped(s * sq) if self.constant_cap is not None else var * (s * sq + b) ** 3  # as diag
        h = g[0] * s
        h += b
        bz = h * h
        bz *= 3.0 * var * s
        h *= 6.0 * var * s * s
        tb = float(s * sq[0] + b)
        f1 = 3.0 * var * tb * tb
        return LocalProfile(k, kd, b=bz, t=h, dg=2.0 * s * f1, dH=4.0 * s * s * (6.0 * var * tb), dI=2.0 * s * f1)

    def mean_terms(self, w):
        # through the moments S_p = sum_m w_m g_m^p, g_m = x.z_m (eq. 11, uncapped as the mean is eq. 8's):
        # sum_m w_m var (s g_m + b)^3 = var (b^3 sum w + 3 b^2 s S1 + 3 b s^2 S2 + s^3 S3)
        var, s_, b = (float(v) for v in np.exp(self.theta))
        return MeanTerms(const=var * b**3 * float(np.sum(w)),
                         moments=(3.0 * var * b * b * s_, 3.0 * var * b * s_ * s_, var * s_**3))

    def diag_local(self, x, ny):
        # k(x, x) = var [(t + b)^3 - b^3] + min(var b^3, cap) (or var (t + b)^3), t = s |x|^2:
        # grad = 3 var (t + b)^2 2 s x, Hessian = 6 var (t + b) 4 s^2 x x^T + 3 var (t + b)^2 2 s I
        var, s, b = (float(v) for v in np.exp(self.theta))
        t = s * float(np.einsum("ij,ij->i", x[None, :], x[None, :])[0])
        if self.constant_cap is not None:  # diag's arithmetic, on one float
            kxx = (t * t + (3.0 * b) * t + 3.0 * b * b) * t * var + min(var * b**3, self.constant_cap)
        else:
            kxx = var * (t + b) ** 3
        xy = x[:ny]
        f1 = 3.0 * var * (t + b) ** 2
        f2 = 6.0 * var * (t + b)
        H = (4.0 * s * s * f2) * np.outer(xy, xy)
        H[np.diag_indices(ny)] += 2.0 * s * f1
        return kxx, (2.0 * s * f1) * xy, H

    redundant = ("scale",)  # var (s x.x' + b)^3 = (var s^3)(x.x' + b/s)^3: s adds a flat direction to eq. 13

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.log([0.1 * var_y, 1.0 / n_dims, 1.0])

    def iter_cross_grads(self, G, sq1, sq2):
        var, s, b = np.exp(self.theta)
        H = G * s                           # s x.x'
        P = H + b                           # s x.x' + b
        P2 = P * P
        yield var * P2 * P                  # d/dlog var = K
        P2 *= 3.0 * var                     # 3 var (s x.x' + b)^2
        H *= P2
        yield H                             # d/dlog s = 3 var P^2 s x.x'
        P2 *= b
        yield P2                            # d/dlog b = 3 var P^2 b

    def diag_and_grads(self, X, q=None):
        # uncapped, as ML-II uses it: var (s |x|^2 + b)^3
        var, s, b = np.exp(self.theta)
        q = np.einsum("ij,ij->i", X, X) if q is None else q
        P = s * q + b
        dp = var * P**3
        return dp, [dp, 3.0 * var * P**2 * (s * q), 3.0 * var * P**2 * b]

    # eq. (11) on a block of the Gram matrix G = x.x' (uncapped: ML-II uses eq. 11 as it is)
    workspace_input = "gram"

    def block_value(self, base, buf):
        var, s, b = np.exp(self.theta)
        P = base * s
        P += b
        t = P * P
        t *= P
        t *= var
        return t

    def block_grad_sums(self, W, base, buf):
        # P = s x.x' + b: sums of W P^3 and W P^2
        _, s, b = np.exp(self.theta)
        P = base * s
        P += b
        t = W * P
        t *= P
        return np.array([np.einsum("ij,ij->", t, P), t.sum()])

    def grads_from_sums(self, sums, tr_w):
        # dK/dlog var = var P^3, dK/dlog b = 3 var b P^2, dK/dlog s = 3 var P^3 - dK/dlog b
        var, _, b = np.exp(self.theta)
        g_var = var * sums[0]
        g_b = 3.0 * var * b * sums[1]
        return [g_var, 3.0 * g_var - g_b, g_b]
