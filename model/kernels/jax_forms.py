"""The kernels' formulas as JAX functions of their log-parameters, for the accelerator backend.

The numpy classes of this package own the formulas the product answers with; these are the same
formulas written for ``jax.numpy`` (traceable, differentiable in theta and in the test point, no
in-place arithmetic), used by ``model.freerun_jax`` and ``model.ml2_jax``. tests/test_backend_jax.py
checks every kernel type here against its class, so the two cannot drift apart.

``jax_kernel(kernel)`` returns a ``JaxKernel`` with three pure functions of a log-parameter vector
``theta`` (the kernel's own ``get_theta()``, parts concatenated as ``Sum`` does):

* ``cross(theta, G, sq1, sq2)``: K(X1, X2) from the Gram matrix G = X1 X2^T and the squared norms
  (``Kernel.from_gram``); a white part adds nothing between points.
* ``diag(theta, sq)``: k(x, x) for points of squared norm sq (``Kernel.diag``).
* ``white(theta)``: the white parts' variance, added on the diagonal of a training covariance.
* ``train_cov(theta, X, noise_var)``: K(X, X) + (white + noise_var) I, the training covariance of eq. 13.

``kernel_structure(kernel)`` names what a compiled program depends on besides theta (the parts' types
and caps): the key of the compiled-program caches.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..backend import require_jax
from .base import SQRT3, Kernel
from .cubic import CubicPolynomial
from .stationary import RBF, Matern32
from .white import White


def _r2(jnp, G, sq1, sq2):
    return jnp.maximum(sq1[..., :, None] + sq2[..., None, :] - 2.0 * G, 0.0)


def _safe_sqrt(jnp, r2):
    """sqrt with a finite gradient at 0 (a training covariance's diagonal)."""
    pos = r2 > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, r2, 1.0)), 0.0)


def _matern32(jnp, th, G, sq1, sq2):
    var, ls = jnp.exp(th[0]), jnp.exp(th[1])
    a = _safe_sqrt(jnp, _r2(jnp, G, sq1, sq2)) * (SQRT3 / ls)
    return var * (1.0 + a) * jnp.exp(-a)


def _rbf(jnp, th, G, sq1, sq2):
    var, ls = jnp.exp(th[0]), jnp.exp(th[1])
    return var * jnp.exp(-0.5 * _r2(jnp, G, sq1, sq2) / (ls * ls))


def _cubic(cap):
    def cross(jnp, th, G, sq1, sq2):
        var, s, b = jnp.exp(th[0]), jnp.exp(th[1]), jnp.exp(th[2])
        t = s * G
        if cap is None:
            h = t + b
            return var * h * h * h
        # the expanded form with the constant term capped (CubicPolynomial._capped)
        return var * t * (t * t + 3.0 * b * t + 3.0 * b * b) + jnp.minimum(var * b**3, cap)
    return cross


def _stationary_diag(jnp, th, sq):
    return jnp.exp(th[0]) * jnp.ones_like(sq)


def _cubic_diag(cap):
    def diag(jnp, th, sq):
        return _cubic(cap)(jnp, th, sq, sq, sq)  # x.x = sq: the cross formula at G = sq
    return diag


@dataclass(frozen=True)
class JaxKernel:
    """A kernel's formulas as pure JAX functions of its log-parameters (see module docstring)."""

    n_params: int
    cross: Callable
    diag: Callable
    white: Callable

    def train_cov(self, theta, X, noise_var):
        """K(X, X) + (white + noise_var) I at standardised rows X (N x D), one Gram product at full precision."""
        jax = require_jax()
        jnp = jax.numpy
        sq = jnp.sum(X * X, axis=1)
        K = self.cross(theta, jnp.matmul(X, X.T, precision=jax.lax.Precision.HIGHEST), sq, sq)
        return K + (self.white(theta) + noise_var) * jnp.eye(X.shape[0], dtype=K.dtype)


def jax_kernel(kernel: Kernel) -> JaxKernel:
    """The JAX twin of ``kernel`` (a ``Sum`` or one of Matern32, RBF, CubicPolynomial, White).

    Raises NotImplementedError naming the kernel type when it has no JAX form."""
    jnp = require_jax().numpy  # 64-bit arrays on

    pieces = []  # (offset, n, cross or None, diag)
    off = 0
    for p in kernel.parts:
        n = len(p.param_names)
        if type(p) is Matern32:
            pieces.append((off, n, _matern32, _stationary_diag, False))
        elif type(p) is RBF:
            pieces.append((off, n, _rbf, _stationary_diag, False))
        elif type(p) is CubicPolynomial:
            pieces.append((off, n, _cubic(p.constant_cap), _cubic_diag(p.constant_cap), False))
        elif type(p) is White:
            pieces.append((off, n, None, _stationary_diag, True))
        else:
            raise NotImplementedError(f"kernel {type(p).__name__} has no JAX form (model/kernels/jax_forms.py); "
                                      "use backend 'numpy'")
        off += n

    def cross(theta, G, sq1, sq2):
        K = jnp.zeros(G.shape, dtype=G.dtype)
        for o, n, f, _, _ in pieces:
            if f is not None:
                K = K + f(jnp, theta[o:o + n], G, sq1, sq2)
        return K

    def diag(theta, sq):
        d = jnp.zeros(sq.shape, dtype=sq.dtype)
        for o, n, _, g, _ in pieces:
            d = d + g(jnp, theta[o:o + n], sq)
        return d

    def white(theta):
        w = 0.0
        for o, _, _, _, is_white in pieces:
            if is_white:
                w = w + jnp.exp(theta[o])
        return w

    return JaxKernel(off, cross, diag, white)


def kernel_structure(kernel: Kernel) -> tuple:
    """The parts' types and constant caps: all a compiled program depends on besides theta."""
    return tuple((type(p).__name__, getattr(p, "constant_cap", None)) for p in kernel.parts)


def kernel_theta(kernel: Kernel) -> np.ndarray:
    """The log-parameter vector the ``JaxKernel`` functions take (parts concatenated)."""
    return np.concatenate([np.asarray(p.get_theta(), dtype=float) for p in kernel.parts])
