"""The Matérn 5/2, a kernel added by declaring its profile alone (model/kernels/stationary.py, ``Matern52``):
its covariance against the textbook formula, every derivative the contracts derive against finite
differences, ML-II, the linearised and Monte Carlo free runs and the JAX form."""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.model.kernels import CONTRACTS, Matern52, kernel_from_dict, make_kernel

SQRT5 = np.sqrt(5.0)


def _direct(X, X2, var, ls):
    out = np.empty((X.shape[0], X2.shape[0]))
    for i, x in enumerate(X):
        for j, z in enumerate(X2):
            a = SQRT5 * np.sqrt(np.sum((x - z) ** 2)) / ls
            out[i, j] = var * (1.0 + a + a * a / 3.0) * np.exp(-a)
    return out


def _fd(f, x, h=1e-6):
    """Central differences of f at x along every coordinate, stacked last."""
    cols = []
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_registered_by_its_spec_and_serialised():
    k = make_kernel("matern52+cubic")
    assert type(k.parts[0]) is Matern52 and all(k.supports(c) for c in CONTRACTS)
    k.set_theta(np.arange(5) * 0.1)
    k2 = kernel_from_dict(k.to_dict())
    X = np.random.default_rng(0).normal(size=(6, 3))
    assert k.to_dict()["parts"][0]["type"] == "Matern52" and np.array_equal(k(X), k2(X))


def test_covariance_is_the_matern52_formula():
    rng = np.random.default_rng(1)
    X, X2 = rng.normal(size=(9, 4)), rng.normal(size=(7, 4))
    k = Matern52(1.7, 1.3)
    ref = _direct(X, X2, 1.7, 1.3)
    assert np.allclose(k(X, X2), ref, rtol=1e-13, atol=0)
    assert np.allclose(k.cross(X, X2), ref, rtol=1e-13, atol=0)
    assert np.allclose(k(X), _direct(X, X, 1.7, 1.3), rtol=1e-13, atol=1e-15)
    assert np.array_equal(k.diag(X), np.full(9, 1.7))


def test_parameter_gradients_match_finite_differences():
    rng = np.random.default_rng(2)
    X, X2 = rng.normal(size=(10, 3)), rng.normal(size=(8, 3))
    k = Matern52(0.8, 1.6)
    th = k.get_theta()

    def K_at(t, X2=None):
        k2 = Matern52()
        k2.set_theta(t)
        return k2(X, X2)

    K, grads = k.K_and_grads(X)
    fd = _fd(lambda t: K_at(t), th)
    assert np.allclose(K, k(X)) and all(np.allclose(grads[j], fd[..., j], rtol=1e-6, atol=1e-9) for j in range(2))
    G = X @ X2.T
    sq1, sq2 = np.einsum("ij,ij->i", X, X), np.einsum("ij,ij->i", X2, X2)
    cross = list(k.iter_cross_grads(G, sq1, sq2))
    fdx = _fd(lambda t: K_at(t, X2), th)
    assert all(np.allclose(cross[j], fdx[..., j], rtol=1e-6, atol=1e-9) for j in range(2))
    d, dg = k.diag_and_grads(X)
    assert np.allclose(d, k.diag(X)) and np.allclose(dg[0], d) and not np.any(dg[1])


def test_input_gradients_and_local_terms_match_finite_differences():
    rng = np.random.default_rng(3)
    D, ny = 5, 3
    Z = rng.normal(size=(20, D))
    Xs = rng.normal(size=(4, D))
    w = rng.normal(size=20)
    k = Matern52(1.1, 1.4)
    x = Xs[0]
    g = k.grad_x(x, Z)
    assert np.allclose(g, _fd(lambda v: k(v[None], Z)[0], x), rtol=1e-6, atol=1e-9)
    ref = np.stack([k.grad_x(xx, Z).T @ w for xx in Xs])
    assert np.allclose(k.grad_dot(Xs, Z, w), ref, rtol=1e-12, atol=1e-14)
    sq1, sq2 = np.einsum("ij,ij->i", Xs, Xs), np.einsum("ij,ij->i", Z, Z)
    Kv, gd = k.value_and_grad_dot(Xs, Z, w, Xs @ Z.T, sq1, sq2)
    assert np.allclose(Kv, k.cross(Xs, Z), rtol=1e-14) and np.allclose(gd, ref, rtol=1e-12, atol=1e-14)
    kv, J, hess = k.local_terms(x, Z, ny)
    assert np.allclose(kv, k(x[None], Z)[0], rtol=1e-13)
    assert np.allclose(J, g[:, :ny], rtol=1e-10, atol=1e-14)
    E = np.eye(D)
    H = np.stack([(k.grad_x(x + 1e-6 * E[i], Z) - k.grad_x(x - 1e-6 * E[i], Z)).T @ w / 2e-6 for i in range(ny)])
    assert np.allclose(hess(w), H[:, :ny], rtol=1e-6, atol=1e-8)
    d0, dg, dH = k.diag_local(x, ny)
    assert d0 == 1.1 and not np.any(dg) and not np.any(dH)


def test_mean_recursion_profile_is_the_covariance():
    rng = np.random.default_rng(4)
    r2 = rng.uniform(0, 6, size=50)
    k = Matern52(0.6, 0.9)
    t = k.mean_terms(rng.normal(size=50))
    (scale, fill), = t.profiles
    f = np.empty(50)
    fill(r2.copy(), f)
    X2 = np.c_[np.sqrt(r2), np.zeros(50)]
    assert scale == pytest.approx(0.6) and np.allclose(scale * f, k(np.zeros((1, 2)), X2)[0], rtol=1e-13)


def test_ml2_workspace_and_sparse_bound_gradients():
    from gpnarx.model.ml2 import NLMLWorkspace, _nlml_and_grad_generic, initial_theta, nlml_and_grad
    from gpnarx.model.vfe import vfe_nlml_and_grad

    rng = np.random.default_rng(5)
    X = rng.normal(size=(140, 3))
    y = np.sin(X[:, 0]) + 0.2 * X[:, 1] + 0.05 * rng.normal(size=140)
    k = make_kernel("matern52+cubic")
    th = initial_theta(k, X, y) + rng.normal(0, 0.2, k.n_params + 1)
    f, g = nlml_and_grad(th, k, X, y, NLMLWorkspace(k, X))
    f0, g0 = _nlml_and_grad_generic(th, k, X, y, float(np.exp(th[-1])))
    assert abs(f - f0) <= 1e-9 * abs(f0) and np.max(np.abs(g - g0)) <= 1e-8 * np.max(np.abs(g0))
    fd = _fd(lambda t: np.array(nlml_and_grad(t, k, X, y)[0]), th)
    assert np.allclose(g, fd, rtol=1e-5, atol=1e-5)
    Z = X[::5].copy()
    _, gv = vfe_nlml_and_grad(th, k, X, y, Z)
    fdv = _fd(lambda t: np.array(vfe_nlml_and_grad(t, k, X, y, Z)[0]), th)
    assert np.allclose(gv, fdv, rtol=1e-4, atol=1e-4)


@pytest.fixture(scope="module")
def fitted():
    """GPNARX with the Matérn 5/2 (ML-II) on a small simulated record, and a second record of that system."""
    from gpnarx.model.estimator import GPNARX

    def system(n, seed):
        rng = np.random.default_rng(seed)
        u = rng.normal(size=n)
        y = np.zeros(n)
        for t in range(2, n):
            y[t] = 0.5 * y[t - 1] - 0.2 * y[t - 2] + np.tanh(u[t - 1]) + 0.2 * u[t - 2] * y[t - 1]
        return u, y

    u, y = system(500, 1)
    y = y + 0.05 * np.std(y) * np.random.default_rng(9).normal(size=y.size)
    m = GPNARX(ny=2, nu=2, kernel="matern52", max_train_points=250, n_restarts=0).fit([(u, y)])
    return m, system(200, 2)


def test_ml2_fit_and_both_free_runs(fitted):
    m, (u2, y2) = fitted
    assert type(m.kernel_) is Matern52 and np.isfinite(m.nlml_)
    lin = m.simulate(u2, method="linear")
    mc = m.simulate(u2, method="mc", n_paths=256, seed=0)
    assert mc.local_steps > 0  # the local model's fused step, from the derived LocalProfile
    for run in (lin, mc):
        assert np.all(np.isfinite(run.mean)) and np.all(run.std > 0)
        fit = 100 * (1 - np.linalg.norm(run.mean - y2) / np.linalg.norm(y2 - y2.mean()))
        assert fit > 80, fit
    assert np.max(np.abs(mc.mean - lin.mean)) < 0.2 * np.std(y2)
    exact = m.simulate(u2, method="mc", n_paths=256, seed=0, local=False)
    assert np.allclose(mc.mean, exact.mean, rtol=0, atol=0.02 * np.std(y2))


def test_jax_form_is_the_numpy_formula(fitted):
    pytest.importorskip("jax")
    import jax.numpy as jnp

    from gpnarx.model.kernels.jax_forms import jax_kernel, kernel_theta

    rng = np.random.default_rng(6)
    X1, X2 = rng.normal(size=(7, 4)), rng.normal(size=(9, 4))
    for k in (Matern52(0.9, 1.7), make_kernel("matern52+cubic").for_posterior(1.0), fitted[0].posterior_.kernel):
        jk, th = jax_kernel(k), jnp.asarray(kernel_theta(k))
        sq1, sq2 = np.einsum("ij,ij->i", X1, X1), np.einsum("ij,ij->i", X2, X2)
        K = np.asarray(jk.cross(th, jnp.asarray(X1 @ X2.T), jnp.asarray(sq1), jnp.asarray(sq2)))
        np.testing.assert_allclose(K, k.cross(X1, X2), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(jk.diag(th, jnp.asarray(sq1))), k.diag(X1), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(jk.train_cov(th, jnp.asarray(X1), 0.0)), k(X1), rtol=1e-10, atol=1e-12)
