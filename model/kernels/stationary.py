"""Stationary kernels var * f(r^2), r = |x - x'|, each declared by its profile f: the Matérn 3/2 of eq. (10),
the Matérn 5/2 and the squared exponential (RBF). ``StationaryProfile`` derives the rest."""
from __future__ import annotations

from fractions import Fraction

import numpy as np

from .base import CONTRACTS, Kernel, LocalProfile, MeanTerms, _gram_parts, _r2_from_gram, squared_distances


def _derivative(P: dict) -> dict:
    return {k - 1: k * c for k, c in P.items() if k}


def _combine(*terms) -> dict:
    """sum of a * P over (a, P) pairs, for polynomials as {power: coefficient}; zero terms dropped."""
    out: dict = {}
    for a, P in terms:
        for k, c in P.items():
            out[k] = out.get(k, 0) + a * c
    return {k: c for k, c in out.items() if c}


def _shift(P: dict, j: int) -> dict:
    return {k + j: c for k, c in P.items()}


def _ascending(P: dict) -> tuple:
    """Coefficients of a polynomial (no negative powers) by ascending power, as floats."""
    return tuple(float(P.get(k, 0)) for k in range(max(P, default=0) + 1))


def _poly(c: tuple, v, into_v: bool = False):
    """sum_k c[k] v^k (len(c) >= 2) by Horner's rule in augmented operators (in place on numpy, rebinding
    on jax.numpy): into v itself with ``into_v`` for degree 1, else a new array. A unit coefficient adds
    no product, a zero one no sum."""
    n = len(c) - 1
    acc = v if into_v and n == 1 else v + 0.0
    if c[n] != 1.0:
        acc *= c[n]
    for k in range(n - 1, -1, -1):
        if c[k]:
            acc += c[k]
        if k:
            acc *= v
    return acc


def _upow(u: np.ndarray, k: int) -> np.ndarray:
    """|u^k| for k != 0; for k < 0, u = 0 counts as 1 (a finite stand-in where the term diverges, as the
    Matérn 3/2's f'' at r = 0)."""
    b = u if k > 0 else np.where(u > 0.0, u, 1.0)
    out = b
    for _ in range(abs(k) - 1):
        out = out * b
    return out


def _safe_sqrt(xp, r2):
    """sqrt with a finite gradient at 0 (JAX differentiates a training covariance's diagonal)."""
    pos = r2 > 0.0
    return xp.where(pos, xp.sqrt(xp.where(pos, r2, 1.0)), 0.0)


class StationaryProfile(Kernel, *CONTRACTS):  # meets every contract of kernels.base
    """A stationary kernel var * f whose profile is a polynomial times an exponential in the scaled distance
    v = g u, u = r^m: f = p(v) exp(-v / m), with m = 1 (the Matérn family, g = kappa / l) or m = 2 (the
    squared exponential, g = kappa^2 / l^2).

    A subclass declares ``poly`` (p's coefficients by ascending power, p(0) = 1 so that k(x, x) = var;
    ``Fraction`` for exact rationals), ``kappa2`` (kappa^2) and ``power`` (m). From them this class derives,
    once per class in rational arithmetic, the profile's derivatives as polynomials in v (negative powers
    allowed) times E = exp(-v / m):

        2 var f'(r^2) = m var g^(2/m) d1(v) E,   4 var f''(r^2) = m^2 var g^(4/m) d2(v) E,   df/dlog l = dl(v) E,

    and from them every contract method: the ML-II workspace as moments sum W E v^k of a distance block, the
    mean recursion's f from r^2 in place, the local model's coefficients, the JAX form with jax.numpy. A
    term d_k v^k of d_j is evaluated as a scalar, m^j d_k var g^(2j/m + k) by repeated products, times the
    array E u^k (u guarded where it divides).
    """

    param_names = ("variance", "lengthscale")
    workspace_input = "distance"
    workspace_buffer = True
    has_local_profile = True
    poly: tuple = (1,)
    kappa2: float = 1
    power: int = 1

    def __init_subclass__(cls, **kw) -> None:
        super().__init_subclass__(**kw)
        m = cls.power
        P = {k: Fraction(c) for k, c in enumerate(cls.poly) if c}
        if m not in (1, 2) or P.get(0) != 1:
            raise TypeError(f"{cls.__name__}: a profile needs power 1 or 2 and poly[0] = 1 (k(x, x) = variance)")
        q = _combine((1, _derivative(P)), (Fraction(-1, m), P))  # df/dv = q(v) E
        s = -1 if m == 1 else 0  # dv/dr^2 = (m / 2) g^(2/m) v^s
        d1 = _shift(q, s)
        d2 = _shift(_combine((1, _derivative(d1)), (Fraction(-1, m), d1)), s)
        cls._f = _ascending(P)
        cls._dl = _ascending(_combine((-m, _shift(q, 1))))  # dv/dlog l = -m v
        # (k, m^j d_k, exponent of g) per term of d_j
        cls._d = {j: tuple((k, float(m ** j * c), 2 * j // m + k) for k, c in sorted(d.items()))
                  for j, d in ((1, d1), (2, d2))}
        cls._d1_uses_u = any(k for k, _, _ in cls._d[1])
        cls._kappa = np.sqrt(float(cls.kappa2))

    def __init__(self, variance: float = 1.0, lengthscale: float = 1.0) -> None:
        self.theta = np.log([variance, lengthscale]).astype(float)

    def _scales(self):
        """(var, g)."""
        var, ls = np.exp(self.theta)
        return var, (self._kappa / ls if self.power == 1 else self.kappa2 / ls**2)

    def _exp(self, v: np.ndarray, out: np.ndarray) -> np.ndarray:
        """E = exp(-v / m) into out."""
        if self.power == 1:
            np.negative(v, out=out)
        else:
            np.multiply(v, -1.0 / self.power, out=out)
        return np.exp(out, out=out)

    def _uvE(self, r2: np.ndarray, keep_u: bool):
        """(u, v, E, var, g) at r^2, which becomes u; v in u's array unless ``keep_u``; E a new array."""
        var, g = self._scales()
        if self.power == 1:
            np.sqrt(r2, out=r2)
        v = r2 * g if keep_u else np.multiply(r2, g, out=r2)
        return r2, v, self._exp(v, np.empty_like(v)), var, g

    def _times_poly(self, c: tuple, v: np.ndarray, E: np.ndarray, var) -> np.ndarray:
        """var c(v) E, in v's array (c of degree 1) or a new one."""
        if len(c) == 1:
            return E * (var * c[0]) if c[0] != 1.0 else E * var
        K = _poly(c, v, into_v=True)
        K *= E
        K *= var
        return K

    def _d_term(self, j: int, u, E, var, g, trailing: bool = False):
        """m^j var g^(2j/m) d_j(v) E (2 var f' for j = 1, 4 var f'' for j = 2) as (array, scalar): with
        ``trailing`` and one term, its scalar is left to the caller (the array is E itself when the term
        has no u), else (the whole array, 1)."""
        out = None
        for k, c, e in self._d[j]:
            s = var
            for _ in range(e):
                s *= g
            if c != 1.0:
                s *= c
            if trailing and len(self._d[j]) == 1:
                return (E if not k else E * _upow(u, k) if k > 0 else E / _upow(u, k)), s
            a = E * s
            if k > 0:
                a *= _upow(u, k)
            elif k < 0:
                a /= _upow(u, k)
            out = a if out is None else out + a
        return out, 1.0

    # the core: covariance, diagonal

    def _value(self, r2: np.ndarray) -> np.ndarray:
        """var f at r^2 (overwritten)."""
        var, g = self._scales()
        if len(self._f) == 1:  # f = E: one scaled exponent, in place
            if self.power == 1:
                np.sqrt(r2, out=r2)
            r2 *= -g / self.power
            np.exp(r2, out=r2)
            r2 *= var
            return r2
        _, v, E, var, _ = self._uvE(r2, False)
        return self._times_poly(self._f, v, E, var)

    def __call__(self, X, X2=None):
        return self._value(squared_distances(X, X2))

    def from_gram(self, G, sq1, sq2):
        return self._value(_r2_from_gram(G, sq1, sq2))

    def diag(self, X):
        return np.full(X.shape[0], np.exp(self.theta[0]))

    # ML-II and the sparse bound: dK/dlog var = K, dK/dlog l = var dl(v) E

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.log([var_y, median_distance])

    def _cross_grads(self, r2):
        _, v, E, var, _ = self._uvE(r2, False)
        K = self._times_poly(self._f, v.copy(), E, var)
        return K, self._times_poly(self._dl, v, E, var)

    def K_and_grads(self, X):
        K, dl = self._cross_grads(squared_distances(X))
        return K, [K.copy(), dl]

    def iter_cross_grads(self, G, sq1, sq2):
        yield from self._cross_grads(_r2_from_gram(G, sq1, sq2))

    def diag_and_grads(self, X, q=None):
        var = float(np.exp(self.theta[0]))
        n = X.shape[0]
        return np.full(n, var), [np.full(n, var), np.zeros(n)]

    def _block_v(self, base, out=None):
        """v on a block of distances r."""
        v = np.multiply(base, self._kappa / np.exp(self.theta[1]), out=out)
        if self.power == 2:
            v *= v
        return v

    def block_value(self, base, buf):
        var = np.exp(self.theta[0])
        if len(self._f) == 1:
            return self._exp(self._block_v(base, buf), buf) * var
        v = self._block_v(base)
        return self._times_poly(self._f, v, self._exp(v, buf), var)

    def block_grad_sums(self, W, base, buf):
        # the moments S_k = sum W E v^k up to the top power of f and dl, combined as f's and dl's coefficients
        v = self._block_v(base)
        t = W * buf
        S = [t.sum()]
        for _ in range(max(len(self._f), len(self._dl)) - 2):
            t *= v
            S.append(t.sum())
        S.append(np.einsum("ij,ij->", t, v))

        def combine(c):  # sum_k c_k S_k by ascending k, a unit coefficient without its product
            return sum(Sk if ck == 1.0 else ck * Sk for Sk, ck in zip(S, c) if ck)

        return np.array([combine(self._f), combine(self._dl)])

    def grads_from_sums(self, sums, tr_w):
        var = np.exp(self.theta[0])
        return [var * sums[0], var * sums[1]]

    # the linearised free run: 2 var f' contracted with weights, and f for the mean recursion

    def grad_x(self, xs, X):
        diff = xs[None, :] - X
        u, _, E, var, g = self._uvE(np.maximum(np.einsum("ij,ij->i", diff, diff), 0.0), True)
        return self._d_term(1, u, E, var, g)[0][:, None] * diff

    def _grad_rows(self, u, E, var, g, Xs, X, w):
        """sum_n w_n 2 var f'(r_rn^2) (xs_r - x_n) for every row r (E overwritten)."""
        a, s = self._d_term(1, u, E, var, g, trailing=True)
        a *= w
        out = a @ X
        out -= a.sum(axis=1)[:, None] * Xs
        out *= -s
        return out

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        G, sq1, sq2 = _gram_parts(Xs, X, G, sq1, sq2)
        u, _, E, var, g = self._uvE(_r2_from_gram(G, sq1, sq2), self._d1_uses_u)
        return self._grad_rows(u, E, var, g, Xs, X, w)

    def value_and_grad_dot(self, Xs, X, w, G, sq1, sq2):
        u, v, E, var, g = self._uvE(_r2_from_gram(G, sq1, sq2), self._d1_uses_u)
        K = self._times_poly(self._f, v, E, var)
        return K, self._grad_rows(u, E, var, g, Xs, X, w)

    def mean_terms(self, w):
        return MeanTerms(profiles=((float(np.exp(self.theta[0])), self._fill()),))

    def _fill(self):
        """fill(a, out): f(r^2) into out from a = r^2 (overwritten), in place."""
        g, c = float(self._scales()[1]), self._f
        if self.power == 2:
            ge = -g / 2.0

            def fill(a, f):
                np.multiply(a, ge, out=f)
                np.exp(f, out=f)
                if len(c) > 1:
                    a *= g
                    f *= _poly(c, a)

            return fill
        alt = tuple(-ck if k % 2 else ck for k, ck in enumerate(c))  # p(v) as a polynomial in a = -v
        ng = -g

        def fill(a, f):
            np.sqrt(a, out=a)
            a *= ng
            np.exp(a, out=f)
            if len(alt) == 2 and alt[1] == -1.0:
                np.subtract(alt[0], a, out=a)
                f *= a
            elif len(alt) > 1:
                f *= _poly(alt, a)

        return fill

    # the Monte Carlo local model: a = q = 2 var f' and p = 4 var f'' at the first row (the expansion point)

    def local_profile(self, r2, g, sq):
        var, gs = self._scales()
        u = np.sqrt(r2) if self.power == 1 else r2
        v = u * gs
        E = self._exp(v, np.empty_like(v))
        a = self._d_term(1, u[0], E[0], var, gs)[0]
        p = self._d_term(2, u[0], E[0], var, gs)[0] if self._d[2] else None
        return LocalProfile(self._times_poly(self._f, v, E, var), np.full(sq.shape[0], var), a=a, p=p, q=a)

    def jax_part(self):
        m, c, kappa, kappa2 = self.power, self._f, float(self._kappa), float(self.kappa2)

        def cross(jnp, th, G, sq1, sq2):
            var, ls = jnp.exp(th[0]), jnp.exp(th[1])
            r2 = jnp.maximum(sq1[..., :, None] + sq2[..., None, :] - 2.0 * G, 0.0)
            v = _safe_sqrt(jnp, r2) * (kappa / ls) if m == 1 else r2 * (kappa2 / (ls * ls))
            E = jnp.exp(-v / m)
            return var * (E if len(c) == 1 else _poly(c, v) * E)

        def diag(jnp, th, sq):
            return jnp.exp(th[0]) * jnp.ones_like(sq)

        return cross, diag, False


class Matern32(StationaryProfile, spec="matern32"):
    """Matérn 3/2, eq. (10): sigma_m^2 (1 + v) exp(-v), v = sqrt(3) r / l."""

    kappa2, poly = 3, (1, 1)


class Matern52(StationaryProfile, spec="matern52"):
    """Matérn 5/2: sigma^2 (1 + v + v^2 / 3) exp(-v), v = sqrt(5) r / l."""

    kappa2, poly = 5, (1, 1, Fraction(1, 3))


class RBF(StationaryProfile, spec="rbf"):
    """Squared exponential: sigma^2 exp(-v / 2), v = r^2 / l^2."""

    power = 2
