"""Stationary kernels: the Matérn 3/2 of eq. (10) and the squared exponential (RBF)."""
from __future__ import annotations

import numpy as np

from .base import (
    CONTRACTS,
    SQRT3,
    Kernel,
    LocalProfile,
    MeanTerms,
    _gram_parts,
    _r2_from_gram,
    squared_distances,
)


class Stationary(Kernel, *CONTRACTS):  # meets every contract of kernels.base
    """What a stationary kernel var * f(r / l) of two parameters shares: k(x, x) = var (so the diagonal,
    its gradients and its local terms are constants), the data-scaled start (var(y), the median
    distance), and, in the ML-II workspace, a block of distances r with one N x N buffer for the kernel's
    exponential and gradients of the form var * (block sums)."""

    param_names = ("variance", "lengthscale")
    workspace_input = "distance"
    workspace_buffer = True

    def __init__(self, variance: float = 1.0, lengthscale: float = 1.0) -> None:
        self.theta = np.log([variance, lengthscale]).astype(float)

    def diag(self, X):
        return np.full(X.shape[0], np.exp(self.theta[0]))

    def diag_local(self, x, ny):
        return float(np.exp(self.theta[0])), np.zeros(ny), np.zeros((ny, ny))

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.log([var_y, median_distance])

    def diag_and_grads(self, X, q=None):
        var = float(np.exp(self.theta[0]))
        n = X.shape[0]
        return np.full(n, var), [np.full(n, var), np.zeros(n)]

    def grads_from_sums(self, sums, tr_w):
        var = np.exp(self.theta[0])
        return [var * sums[0], var * sums[1]]


class Matern32(Stationary):
    """Matérn 3/2 kernel, eq. (10): sigma_m^2 (1 + sqrt(3) r/l) exp(-sqrt(3) r/l)."""


    def __call__(self, X, X2=None):
        var, ls = np.exp(self.theta)
        a = np.sqrt(squared_distances(X, X2))
        a *= SQRT3 / ls
        K = 1.0 + a
        K *= np.exp(-a)
        K *= var
        return K

    def K_and_grads(self, X):
        var, ls = np.exp(self.theta)
        a = np.sqrt(squared_distances(X)) * (SQRT3 / ls)
        e = np.exp(-a)
        K = var * (1.0 + a) * e
        dls = var * a * a * e  # dk/dlog l = sigma^2 a^2 exp(-a)
        return K, [K.copy(), dls]

    def from_gram(self, G, sq1, sq2):
        var, ls = np.exp(self.theta)
        a = _r2_from_gram(G, sq1, sq2)
        np.sqrt(a, out=a)
        a *= SQRT3 / ls
        K = 1.0 + a
        np.negative(a, out=a)
        np.exp(a, out=a)
        K *= a
        K *= var
        return K

    def grad_x(self, xs, X):
        var, ls = np.exp(self.theta)
        diff = xs[None, :] - X
        a = np.sqrt(np.maximum(np.einsum("ij,ij->i", diff, diff), 0.0)) * (SQRT3 / ls)
        # dk/dxs = -sigma^2 (3 / l^2) exp(-a) (xs - x)
        return (-var * 3.0 / ls**2 * np.exp(-a))[:, None] * diff

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        # sum_n w_n dk/dxs = -sigma^2 (3 / l^2) [(E w) xs - E (w * X)], E = exp(-a) (rows x N)
        var, ls = np.exp(self.theta)
        G, sq1, sq2 = _gram_parts(Xs, X, G, sq1, sq2)
        E = _r2_from_gram(G, sq1, sq2)
        np.sqrt(E, out=E)
        E *= -SQRT3 / ls
        np.exp(E, out=E)
        E *= w
        out = E @ X
        out -= E.sum(axis=1)[:, None] * Xs
        out *= var * 3.0 / ls**2
        return out

    def value_and_grad_dot(self, Xs, X, w, G, sq1, sq2):
        # one sqrt and one exp for both: K = var (1 + a) e, e = exp(-a); the gradient as grad_dot
        var, ls = np.exp(self.theta)
        a = _r2_from_gram(G, sq1, sq2)
        np.sqrt(a, out=a)
        a *= SQRT3 / ls
        E = np.negative(a)
        np.exp(E, out=E)
        a += 1.0
        a *= E
        a *= var  # K
        E *= w
        out = E @ X
        out -= E.sum(axis=1)[:, None] * Xs
        out *= var * 3.0 / ls**2
        return a, out

    def local_terms(self, x, X, ny):
        # with d = x - x_n, r = |d|, c = sqrt(3) / l, e = exp(-c r) (eq. 10):
        # grad = -var c^2 e d, Hessian = -var c^2 e (I - c d d^T / r)
        var, ls = np.exp(self.theta)
        c = SQRT3 / ls
        k = self.cross(x[None, :], X)[0]
        Dy = x[None, :ny] - X[:, :ny]
        d = x[None, :] - X
        r = np.sqrt(np.einsum("ij,ij->i", d, d))
        e = np.exp(-c * r)
        J = (-var * c * c * e)[:, None] * Dy
        rs = np.where(r > 0.0, r, 1.0)

        def hess(beta):
            be = beta * e
            H = Dy.T @ ((be * (c / rs))[:, None] * Dy)
            H[np.diag_indices(ny)] -= be.sum()
            return (var * c * c) * H

        return k, J, hess

    def local_profile(self, r2, g, sq):
        # local_terms' coefficients: e = exp(-c r); a = q = -var c^2 e, p = var c^3 e / r
        # (k as from_gram: var (1 + a) exp(-a), a = c r)
        var, ls = np.exp(self.theta)
        c = SQRT3 / ls
        r = np.sqrt(r2)
        k = r * c
        e = np.exp(-k)
        k += 1.0
        k *= e
        k *= var
        a = e[0] * (-var * c * c)
        p = e[0] * (var * c * c * c)
        p /= np.where(r[0] > 0.0, r[0], 1.0)
        return LocalProfile(k, np.full(sq.shape[0], var), a=a, p=p, q=a)

    def mean_terms(self, w):
        # (1 + a) exp(-a), a = sqrt(3) r / l (eq. 10), from a = r^2; the variance scales the sum
        var, ls = np.exp(self.theta)
        c = float(SQRT3 / ls)

        def fill(a, f):
            np.sqrt(a, out=a)
            a *= -c
            np.exp(a, out=f)
            np.subtract(1.0, a, out=a)
            f *= a

        return MeanTerms(profiles=((float(var), fill),))

    def iter_cross_grads(self, G, sq1, sq2):
        var, ls = np.exp(self.theta)
        a = _r2_from_gram(G, sq1, sq2)
        np.sqrt(a, out=a)
        a *= SQRT3 / ls
        e = np.exp(-a)
        yield var * (1.0 + a) * e           # d/dlog var = K
        a *= a
        a *= e
        a *= var
        yield a                             # d/dlog l = var a^2 exp(-a)

    # workspace: eq. (10) on a block of distances r, a = sqrt(3) r / l, K = var (1 + a) e^-a with e^-a in buf

    def block_value(self, base, buf):
        var, ls = np.exp(self.theta)
        a = base * (SQRT3 / ls)
        np.negative(a, out=buf)
        np.exp(buf, out=buf)
        a += 1.0
        a *= buf
        a *= var
        return a

    def block_grad_sums(self, W, base, buf):
        # dK/dlog var = K = var (1 + a) e^-a, dK/dlog l = var a^2 e^-a: sums of W e^-a (1 + a) and W e^-a a^2
        a = base * (SQRT3 / np.exp(self.theta[1]))
        t = W * buf
        s0 = t.sum()
        t *= a
        s1 = t.sum()
        return np.array([s0 + s1, np.einsum("ij,ij->", t, a)])


class RBF(Stationary):
    """Squared-exponential kernel: sigma^2 exp(-r^2 / (2 l^2))."""


    def __call__(self, X, X2=None):
        var, ls = np.exp(self.theta)
        r2 = squared_distances(X, X2)
        r2 *= -0.5 / ls**2
        np.exp(r2, out=r2)
        r2 *= var
        return r2

    def K_and_grads(self, X):
        var, ls = np.exp(self.theta)
        r2 = squared_distances(X) / ls**2
        K = var * np.exp(-0.5 * r2)
        return K, [K.copy(), K * r2]

    def from_gram(self, G, sq1, sq2):
        var, ls = np.exp(self.theta)
        r2 = _r2_from_gram(G, sq1, sq2)
        r2 *= -0.5 / ls**2
        np.exp(r2, out=r2)
        r2 *= var
        return r2

    def grad_x(self, xs, X):
        var, ls = np.exp(self.theta)
        diff = xs[None, :] - X
        k = var * np.exp(-0.5 * np.einsum("ij,ij->i", diff, diff) / ls**2)
        return (-k / ls**2)[:, None] * diff

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        # sum_n w_n dk/dxs = -(1 / l^2) [(K w) xs - K (w * X)]
        G, sq1, sq2 = _gram_parts(Xs, X, G, sq1, sq2)
        K = self.from_gram(G, sq1, sq2)
        K *= w
        out = K @ X
        out -= K.sum(axis=1)[:, None] * Xs
        out *= 1.0 / np.exp(self.theta[1]) ** 2
        return out

    def local_terms(self, x, X, ny):
        # grad = -k d / l^2, Hessian = k (d d^T / l^4 - I / l^2), d = x - x_n
        ls2 = np.exp(self.theta[1]) ** 2
        k = self.cross(x[None, :], X)[0]
        Dy = x[None, :ny] - X[:, :ny]
        J = (-k / ls2)[:, None] * Dy

        def hess(beta):
            bk = beta * k
            H = Dy.T @ (bk[:, None] * Dy) / (ls2 * ls2)
            H[np.diag_indices(ny)] -= bk.sum() / ls2
            return H

        return k, J, hess

    def local_profile(self, r2, g, sq):
        # local_terms' coefficients: a = q = -k / l^2, p = k / l^4
        var, ls = np.exp(self.theta)
        ls2 = ls * ls
        k = np.exp(r2 * (-0.5 / ls2))
        k *= var
        a = k[0] * (-1.0 / ls2)
        return LocalProfile(k, np.full(sq.shape[0], var), a=a, p=k[0] * (1.0 / (ls2 * ls2)), q=a)

    def mean_terms(self, w):
        # exp(-r^2 / (2 l^2)) from a = r^2; the variance scales the sum
        var, ls = np.exp(self.theta)
        c = float(-0.5 / ls**2)

        def fill(a, f):
            np.multiply(a, c, out=f)
            np.exp(f, out=f)

        return MeanTerms(profiles=((float(var), fill),))

    def iter_cross_grads(self, G, sq1, sq2):
        var, ls = np.exp(self.theta)
        r2 = _r2_from_gram(G, sq1, sq2)
        r2 /= ls**2
        K = np.exp(-0.5 * r2)
        K *= var
        yield K                             # d/dlog var = K
        r2 *= K
        yield r2                            # d/dlog l = K r^2 / l^2

    # workspace: K = var exp(-(r/l)^2 / 2) on a block of distances r, exp(...) kept in buf

    def block_value(self, base, buf):
        var, ls = np.exp(self.theta)
        np.multiply(base, 1.0 / ls, out=buf)
        buf *= buf
        buf *= -0.5
        np.exp(buf, out=buf)
        return buf * var

    def block_grad_sums(self, W, base, buf):
        # dK/dlog var = K, dK/dlog l = K r^2 / l^2: sums of W exp(.) and W exp(.) r^2 / l^2
        t = W * buf
        r2 = base * (1.0 / np.exp(self.theta[1]))
        r2 *= r2
        return np.array([t.sum(), np.einsum("ij,ij->", t, r2)])
