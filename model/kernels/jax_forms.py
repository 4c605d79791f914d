"""The kernels' formulas as JAX functions of their log-parameters, for the accelerator backend.

The numpy classes of this package own the formulas the product answers with; their JAX forms evaluate
the same formulas with ``jax.numpy`` (traceable, differentiable in theta and in the test point), used by
``model.freerun.jax_backend`` and ``model.ml2_jax``. tests/test_backend_jax.py checks every kernel type
against its class.

Each kernel gives its JAX form through ``Kernel.jax_part`` (the family bases evaluate the declared
formula with jax.numpy). ``jax_kernel(kernel)`` returns a ``JaxKernel`` with three pure functions of a
log-parameter vector ``theta`` (the kernel's own ``get_theta()``, parts concatenated as ``Sum`` does):

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
from .base import Kernel


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
    """The JAX twin of ``kernel`` (a ``Sum`` or one kernel), from each part's ``Kernel.jax_part``.

    Raises NotImplementedError naming the kernel type when a part has no JAX form."""
    jnp = require_jax().numpy  # 64-bit arrays on

    pieces = []  # (offset, n, cross or None, diag, white)
    off = 0
    for p in kernel.parts:
        n = len(p.param_names)
        part = p.jax_part()
        if part is None:
            raise NotImplementedError(f"kernel {type(p).__name__} has no JAX form (Kernel.jax_part); "
                                      "use backend 'numpy'")
        pieces.append((off, n, *part))
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
