"""ML-II (eq. 13) and the exact posterior's solves on the JAX backend, for N of 10-20 thousand rows.

``nlml_and_grad_jax`` is the negative log marginal likelihood of the exact GP and its gradient in
the log-hyperparameters (kernel's, then log sigma_y^2), by ``jax.value_and_grad`` through one
Cholesky factorisation, float64, compiled once per kernel structure and N. ``ml2.fit_ml2`` takes
it as its objective for ``backend="jax"``: the same L-BFGS-B, restarts, warm start and bounds as
the numpy workspace (``ml2.NLMLWorkspace``). On a GPU an evaluation at N = 16,000 is a fraction of
a second; on two CPU cores it is minutes, which is why the numpy default subsamples to
``max_train_points``.

``exact_solve_jax`` returns the exact posterior's alpha = (K + sigma_y^2 I)^-1 y and L^-1 (eq. 8-9),
for ``gp.ExactPosterior``.
"""
from __future__ import annotations

import numpy as np

from .backend import require_jax
from .kernels.jax_forms import jax_kernel, kernel_structure, kernel_theta
from .linalg import JITTERS, NotPositiveDefiniteError

_CACHE: dict = {}


def _program(kernel):
    key = kernel_structure(kernel)
    if key in _CACHE:
        return _CACHE[key]
    jax = require_jax()
    jnp = jax.numpy
    jk = jax_kernel(kernel)
    nk = jk.n_params

    def nlml(theta, X, y, rel_jitter):
        K = jk.train_cov(theta[:nk], X, jnp.exp(theta[nk]))
        K = K + jax.lax.stop_gradient(rel_jitter * jnp.mean(jnp.diag(K))) * jnp.eye(X.shape[0], dtype=K.dtype)
        L = jnp.linalg.cholesky(K)
        a = jax.scipy.linalg.cho_solve((L, True), y)
        return 0.5 * jnp.dot(y, a) + jnp.sum(jnp.log(jnp.diag(L))) + 0.5 * y.size * jnp.log(2.0 * jnp.pi)

    prog = _CACHE[key] = jax.jit(jax.value_and_grad(nlml))
    return prog


def nlml_and_grad_jax(theta, kernel, X, y):
    """eq. 13's negative log marginal likelihood and its gradient at ``theta`` (kernel log-parameters,
    then log sigma_y^2), exact GP on standardised X (N x D), y (N,). Raises ``NotPositiveDefiniteError``
    when the Cholesky factorisation fails with every jitter of ``linalg.JITTERS`` (relative to the mean
    diagonal, escalated as the numpy workspace does; ``ml2.multistart_lbfgsb`` keeps the start's best
    point)."""
    jax = require_jax()
    X, y = _on_device(jax, X, y)
    th = jax.numpy.asarray(theta, dtype=jax.numpy.float64)
    for rel in JITTERS:
        val, grad = _program(kernel)(th, X, y, rel)
        val, grad = float(val), np.asarray(grad, dtype=float)
        if np.isfinite(val) and np.all(np.isfinite(grad)):
            return val, grad
    raise NotPositiveDefiniteError(f"the training covariance (N={X.shape[0]}) is not positive definite even with "
                                   f"jitter {JITTERS[-1]:g} x mean diagonal")


_DEVICE_DATA: dict = {}


def _on_device(jax, X, y):
    """X and y as device arrays, copied once per array (L-BFGS-B calls the objective many times)."""
    key = (id(X), id(y), X.shape)
    hit = _DEVICE_DATA.get(key)
    if hit is None or hit[0] is not X:
        _DEVICE_DATA.clear()
        hit = _DEVICE_DATA[key] = (X, jax.numpy.asarray(X, dtype=jax.numpy.float64),
                                   jax.numpy.asarray(y, dtype=jax.numpy.float64))
    return hit[1], hit[2]


def exact_solve_jax(kernel, noise_var: float, X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, Linv) of the exact posterior (``gp.ExactPosterior``), float64, on the JAX device."""
    jax = require_jax()
    jnp = jax.numpy
    theta = jnp.asarray(kernel_theta(kernel), dtype=jnp.float64)
    yd = jnp.asarray(y, dtype=jnp.float64)
    K = jax_kernel(kernel).train_cov(theta, jnp.asarray(X, dtype=jnp.float64), noise_var)
    scale = float(jnp.mean(jnp.diag(K)))
    for rel in JITTERS:
        L = jnp.linalg.cholesky(K + (rel * scale) * jnp.eye(X.shape[0], dtype=K.dtype) if rel else K)
        if bool(jnp.all(jnp.isfinite(jnp.diag(L)))):
            break
    else:
        raise NotPositiveDefiniteError(f"the training covariance (N={X.shape[0]}) is not positive definite even "
                                       f"with jitter {JITTERS[-1]:g} x mean diagonal")
    alpha = jax.scipy.linalg.cho_solve((L, True), yd)
    Linv = jax.scipy.linalg.solve_triangular(L, jnp.eye(X.shape[0], dtype=L.dtype), lower=True)
    return np.asarray(alpha), np.tril(np.asarray(Linv))


def predict_exact_jax(posterior, Xs: np.ndarray, block: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """eq. 8-9 of a posterior (``posterior.Posterior``: K(x, points) w and k(x, x) - |F k|^2, as
    ``gp.ExactPosterior.predict``) at the rows of Xs, float64, on the JAX device in row blocks: the held-out
    noise calibration of an exact posterior of N = 10-20 thousand rows."""
    jax = require_jax()
    jnp = jax.numpy
    key = ("predict", kernel_structure(posterior.kernel))
    prog = _CACHE.get(key)
    if prog is None:
        jk = jax_kernel(posterior.kernel)
        hi = jax.lax.Precision.HIGHEST

        def program(theta, xb, X, sqX, alpha, LinvT, shift):
            sq = jnp.sum(xb * xb, axis=1)
            K = jk.cross(theta, jnp.matmul(xb, X.T, precision=hi), sq, sqX)
            V = jnp.matmul(K, LinvT, precision=hi)
            return jnp.matmul(K, alpha, precision=hi) + shift, jk.diag(theta, sq) - jnp.sum(V * V, axis=1)

        prog = _CACHE[key] = jax.jit(program)
    d = lambda a: jnp.asarray(a, dtype=jnp.float64)  # noqa: E731
    X = posterior.points
    args = (d(X), d(np.einsum("ij,ij->i", X, X)), d(posterior.mean_weights), d(posterior.variance_factor.T),
            d(posterior.mean_shift))
    theta = d(kernel_theta(posterior.kernel))
    Xs = np.asarray(Xs, dtype=float)
    mean, var = np.empty(Xs.shape[0]), np.empty(Xs.shape[0])
    for r0 in range(0, Xs.shape[0], block):
        xb = Xs[r0:r0 + block]
        pad = np.zeros((block, Xs.shape[1]))
        pad[: xb.shape[0]] = xb  # one compiled shape for every block
        m, v = prog(theta, d(pad), *args)
        mean[r0:r0 + xb.shape[0]] = np.asarray(m)[: xb.shape[0]]
        var[r0:r0 + xb.shape[0]] = np.asarray(v)[: xb.shape[0]]
    return mean, np.maximum(var, 1e-300)
