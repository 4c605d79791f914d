"""Dot-product kernels var * (s x.x' + b)^p, each declared by its degree p: the cubic polynomial of eq. (11).
``DotProductProfile`` derives the rest, with the optional cap on the constant term."""
from __future__ import annotations

from math import comb

import numpy as np

from .base import CONTRACTS, Kernel, LocalProfile, MeanTerms

DEFAULT_CONSTANT_CAP = 1.0  # variance of the standardised output; GPNARX(constant_cap=...) default


def check_constant_cap(cap, name: str = "constant_cap") -> float | None:
    """``cap`` as a float (or None); anything else that is not a finite positive number is refused."""
    if cap is not None and (isinstance(cap, bool) or not isinstance(cap, (int, float, np.floating))
                            or not np.isfinite(cap) or cap <= 0):
        raise ValueError(f"{name} must be a positive number or None, got {cap!r}")
    return None if cap is None else float(cap)


def _power(h, n: int):
    """h^n (n >= 0) by repeated products, as a new array (in place on numpy, rebinding on jax.numpy)."""
    if n == 0:
        return h * 0.0 + 1.0
    out = h * h if n >= 2 else h + 0.0
    for _ in range(n - 2):
        out *= h
    return out


def _expanded(T, var, b, p: int, cap, minimum):
    """var [(T + b)^p - b^p] + minimum(var b^p, cap) at T = s t: the terms C(p, k) b^(p-k) T^(k-1) by
    descending k, times T, times var (augmented operators: in place on numpy, rebinding on jax.numpy)."""
    K = _power(T, p - 1)
    for k in range(p - 1, 0, -1):
        c = float(comb(p, k))
        for _ in range(p - k):
            c = c * b
        if k == 1:
            K += c
        else:
            K += c * (T if k == 2 else _power(T, k - 1))
    K *= T
    K *= var
    K += minimum(var * b**p, cap)
    return K


class DotProductProfile(Kernel, *CONTRACTS):  # meets every contract of kernels.base
    """A dot-product kernel var * h^p, h = s t + b with t = x.x', of a degree p the subclass declares
    (``degree``); this class derives from it every contract method, in t, g = x . X_n and |x|^2.

    Expanded, var (T + b)^p = var [(T + b)^p - b^p] + var b^p with T = s t: a constant term var b^p (the
    prior variance of a constant offset) plus terms that vanish at t = 0. ML-II (eq. 13) on standardised
    data can drive b up while the likelihood stays flat in that offset's variance, and the predictive
    variance k(x,x) - k A k then cancels below float64 precision. ``constant_cap`` (standardised output
    variance; None = no cap) replaces the constant term by min(var b^p, constant_cap) and evaluates the
    rest in the expanded form, without that cancellation. Posteriors take their variance from the capped
    kernel and their mean from the uncapped one (the two differ by the constant ``cap_shift()``); ML-II
    uses the uncapped kernel, so the hyperparameters and the predicted means are eq. 13's and eq. 8's.
    The mean recursion's moments need p <= 3.
    """

    param_names = ("variance", "scale", "bias")
    workspace_input = "gram"
    has_local_profile = True
    redundant = ("scale",)  # var (s t + b)^p = (var s^p)(t + b/s)^p: s adds a flat direction to eq. 13
    degree: int = 1

    def __init__(self, variance: float = 1.0, scale: float = 1.0, bias: float = 1.0,
                 constant_cap: float | None = None) -> None:
        self.theta = np.log([variance, scale, bias]).astype(float)
        self.constant_cap = None if constant_cap is None else float(constant_cap)

    def _capped(self, T: np.ndarray) -> np.ndarray:
        var, _, b = np.exp(self.theta)
        return _expanded(T, var, b, self.degree, self.constant_cap, min)

    def from_gram(self, G, sq1, sq2):
        var, s, b = np.exp(self.theta)
        H = G * s
        if self.constant_cap is not None:
            return self._capped(H)
        H += b
        K = _power(H, self.degree)
        K *= var
        return K

    def __call__(self, X, X2=None):
        return self.from_gram(X @ (X if X2 is None else X2).T, None, None)  # G is enough

    def diag(self, X):
        var, s, b = np.exp(self.theta)
        if self.constant_cap is not None:
            return self._capped(s * np.einsum("ij,ij->i", X, X))
        return var * (s * np.einsum("ij,ij->i", X, X) + b) ** self.degree

    def cap_shift(self) -> float:
        if self.constant_cap is None:
            return 0.0
        var, _, b = np.exp(self.theta)
        return max(float(var * b**self.degree) - self.constant_cap, 0.0)

    def for_posterior(self, constant_cap: float | None = None) -> "DotProductProfile":
        k = self.clone()
        k.constant_cap = None if constant_cap is None else float(constant_cap)
        return k

    def to_dict(self) -> dict:
        d = super().to_dict()
        if self.constant_cap is not None:
            d["constant_cap"] = self.constant_cap
        return d

    def read_extra(self, d: dict) -> None:
        self.constant_cap = check_constant_cap(d.get("constant_cap"), f"kernel {type(self).__name__} constant_cap")

    # ML-II and the sparse bound (uncapped): dK/dlog var = K, dK/dlog s = p var h^(p-1) s t,
    # dK/dlog b = p var h^(p-1) b

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.log([0.1 * var_y, 1.0 / n_dims, 1.0])

    def iter_cross_grads(self, G, sq1, sq2):
        var, s, b = np.exp(self.theta)
        H = G * s
        P = H + b
        Q = _power(P, self.degree - 1)
        yield var * Q * P
        Q *= self.degree * var
        H *= Q
        yield H
        Q *= b
        yield Q

    def K_and_grads(self, X):
        if self.constant_cap is not None:
            raise ValueError("a kernel with constant_cap is for posteriors; ML-II uses the uncapped kernel")
        K, *grads = self.iter_cross_grads(X @ X.T, None, None)
        return K, [K.copy(), *grads]

    def diag_and_grads(self, X, q=None):
        var, s, b = np.exp(self.theta)
        p = self.degree
        q = np.einsum("ij,ij->i", X, X) if q is None else q
        P = s * q + b
        dp = var * P**p
        return dp, [dp, p * var * P ** (p - 1) * (s * q), p * var * P ** (p - 1) * b]

    def block_value(self, base, buf):
        var, s, b = np.exp(self.theta)
        P = base * s
        P += b
        t = _power(P, self.degree)
        t *= var
        return t

    def block_grad_sums(self, W, base, buf):
        # P = s t + b: sums of W P^p and W P^(p-1)
        _, s, b = np.exp(self.theta)
        P = base * s
        P += b
        t = W * P if self.degree > 1 else W
        for _ in range(self.degree - 2):
            t *= P
        return np.array([np.einsum("ij,ij->", t, P), t.sum()])

    def grads_from_sums(self, sums, tr_w):
        # dK/dlog var = var P^p, dK/dlog b = p var b P^(p-1), dK/dlog s = p dK/dlog var - dK/dlog b
        var, _, b = np.exp(self.theta)
        g_var = var * sums[0]
        g_b = self.degree * var * b * sums[1]
        return [g_var, self.degree * g_var - g_b, g_b]

    # the linearised free run: d k / d x = p var s h^(p-1) x_n (the capped constant has no gradient)

    def grad_x(self, xs, X):
        var, s, b = np.exp(self.theta)
        h = s * (X @ xs) + b
        c = self.degree * var * s
        for _ in range(self.degree - 1):
            c = c * h
        return (c if np.ndim(c) else np.full(X.shape[0], c))[:, None] * X

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        var, s, b = np.exp(self.theta)
        H = (Xs @ X.T if G is None else G) * s
        H += b
        H = _power(H, self.degree - 1)
        H *= (self.degree * var * s) * w
        return H @ X

    def mean_terms(self, w):
        # sum_m w_m var (s g_m + b)^p = var sum_k C(p, k) b^(p-k) s^k S_k with S_k = sum_m w_m g_m^k, g_m = x.z_m
        # (uncapped: the mean is eq. 8's); the pure powers as powers, the mixed terms as products
        p = self.degree
        if p > 3:
            return None
        var, s, b = (float(v) for v in np.exp(self.theta))
        moments = [0.0, 0.0, 0.0]
        for k in range(1, p + 1):
            if k == p:
                moments[k - 1] = var * s**p
                continue
            c = comb(p, k) * var
            for _ in range(p - k):
                c *= b
            for _ in range(k):
                c *= s
            moments[k - 1] = c
        return MeanTerms(const=var * b**p * float(np.sum(w)), moments=tuple(moments))

    # the Monte Carlo local model: h = s g + b; b_n = p var s h^(p-1), t_n = p (p-1) var s^2 h^(p-2); with
    # tb = s |x|^2 + b: dg = dI = 2 s p var tb^(p-1), dH = 4 s^2 p (p-1) var tb^(p-2)

    def local_profile(self, r2, g, sq):
        var, s, b = np.exp(self.theta)
        p = self.degree
        k = self.from_gram(g, None, None)
        kd = self._capped(s * sq) if self.constant_cap is not None else var * (s * sq + b) ** p
        h = g[0] * s
        h += b
        bz = _power(h, p - 1)
        bz *= p * var * s
        t = None
        if p >= 2:
            t = _power(h, p - 2)
            t *= p * (p - 1) * var * s * s
        tb = float(s * sq[0] + b)
        f1 = p * var
        for _ in range(p - 1):
            f1 *= tb
        f2 = p * (p - 1) * var
        for _ in range(p - 2):
            f2 *= tb
        return LocalProfile(k, kd, b=bz, t=t, dg=2.0 * s * f1, dH=4.0 * s * s * f2, dI=2.0 * s * f1)

    def jax_part(self):
        p, cap = self.degree, self.constant_cap

        def cross(jnp, th, G, sq1, sq2):
            var, s, b = jnp.exp(th[0]), jnp.exp(th[1]), jnp.exp(th[2])
            T = s * G
            if cap is None:
                return var * _power(T + b, p)
            return _expanded(T, var, b, p, cap, jnp.minimum)

        def diag(jnp, th, sq):
            return cross(jnp, th, sq, sq, sq)  # x.x = sq: the cross formula at G = sq

        return cross, diag, False


class CubicPolynomial(DotProductProfile, spec="cubic"):
    """Cubic polynomial kernel, eq. (11): sigma_p^2 (s x.x' + b)^3."""

    degree = 3
