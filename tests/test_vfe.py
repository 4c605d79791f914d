"""Sparse ML-II with the Titsias VFE bound (model/vfe.py): gradients, exactness at Z = X, bound
property, hyperparameter recovery on a toy problem and a timing printout."""
import itertools
import time

import numpy as np
import pytest

from gpnarx.model.gp import SparsePosterior, choose_inducing
from gpnarx.model.kernels import RBF, CubicPolynomial, Matern32, White, make_kernel
from gpnarx.model.ml2 import MLIIResult, initial_theta, nlml_and_grad
from gpnarx.model.vfe import cross_grads, diag_grads, fit_vfe, vfe_nlml_and_grad


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Run this module's linear algebra on one BLAS thread: on a shared, oversubscribed machine
    multi-threaded OpenBLAS is several times slower, and the timings printed below stay comparable."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _data(N=200, D=5, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(N, D))
    y = np.sin(X[:, 0]) + 0.3 * X[:, 1] ** 2 - 0.2 * X[:, 2] * X[:, 3] + 0.1 * rng.normal(size=N)
    return X, y - y.mean()


def _fd_grad(f, th, h=1e-5):
    g = np.empty_like(th)
    for j in range(th.size):
        e = np.zeros_like(th)
        e[j] = h
        g[j] = (f(th + e) - f(th - e)) / (2 * h)
    return g


@pytest.mark.parametrize("kernel", [Matern32(1.2, 0.8), RBF(0.7, 1.5), CubicPolynomial(0.3, 0.5, 1.1), White(0.2),
                                    Matern32() + CubicPolynomial() + White(0.1)])
def test_cross_and_diag_grads_match_finite_differences(kernel):
    rng = np.random.default_rng(1)
    Z, X = rng.normal(size=(7, 4)), rng.normal(size=(11, 4))
    K, grads = cross_grads(kernel, Z, X)
    d, dgrads = diag_grads(kernel, X)
    assert np.allclose(K, kernel(Z, X), rtol=1e-12, atol=1e-12)
    assert np.allclose(d, kernel.diag(X), rtol=1e-12)
    assert len(grads) == len(dgrads) == kernel.n_params
    th = kernel.get_theta()
    for j in range(th.size):
        e = np.zeros_like(th)
        e[j] = 1e-6
        kernel.set_theta(th + e)
        Kp, dp = kernel(Z, X), kernel.diag(X)
        kernel.set_theta(th - e)
        Km, dm = kernel(Z, X), kernel.diag(X)
        kernel.set_theta(th)
        assert np.allclose(grads[j], (Kp - Km) / 2e-6, rtol=1e-6, atol=1e-8)
        assert np.allclose(dgrads[j], (dp - dm) / 2e-6, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("spec", ["matern32+cubic", "rbf"])
def test_vfe_gradient_matches_finite_differences(spec):
    X, y = _data()
    Z = choose_inducing(X, 20, seed=0)
    k = make_kernel(spec)
    rng = np.random.default_rng(2)
    for trial in range(2):
        th = initial_theta(k, X, y) + rng.normal(0.0, 0.3, k.n_params + 1)
        f, g = vfe_nlml_and_grad(th, k, X, y, Z)
        fd = _fd_grad(lambda t: vfe_nlml_and_grad(t, k, X, y, Z)[0], th)
        assert np.isfinite(f)
        # per component, relative (floored at 1e-3 of the largest component for near-zero ones)
        err = np.abs(g - fd) / np.maximum(np.abs(fd), 1e-3 * np.max(np.abs(fd)))
        assert np.max(err) < 1e-5, (spec, trial, g, fd)


@pytest.mark.parametrize("spec", ["matern32+cubic", "rbf"])
def test_bound_equals_exact_likelihood_when_inducing_inputs_are_the_data(spec):
    X, y = _data()
    k = make_kernel(spec)
    th = initial_theta(k, X, y)
    exact, gexact = nlml_and_grad(th, k, X, y)
    # no Kmm jitter: Qnn = Knn exactly
    f, g = vfe_nlml_and_grad(th, k, X, y, X, jitter=0.0)
    assert abs(f - exact) < 1e-6 * max(1.0, abs(exact))
    assert np.max(np.abs(g - gexact)) < 1e-6 * np.max(np.abs(gexact))
    # the default relative jitter (1e-8 mean diag Kmm) perturbs it at the O(N * jitter / s2) level
    f8, _ = vfe_nlml_and_grad(th, k, X, y, X)
    assert abs(f8 - exact) < 1e-3 + 1e-6 * abs(exact)


@pytest.mark.parametrize("spec", ["matern32+cubic", "rbf"])
def test_bound_is_below_exact_likelihood(spec):
    X, y = _data()
    k = make_kernel(spec)
    rng = np.random.default_rng(3)
    for m in (5, 20, 80):
        Z = choose_inducing(X, m, seed=m)
        for _ in range(3):
            th = initial_theta(k, X, y) + rng.normal(0.0, 0.5, k.n_params + 1)
            neg_bound, _ = vfe_nlml_and_grad(th, k, X, y, Z)
            exact, _ = nlml_and_grad(th, k, X, y)
            assert neg_bound >= exact - 1e-8 * abs(exact)


def test_bound_tightens_with_more_inducing_points():
    X, y = _data()
    k = make_kernel("rbf")
    th = initial_theta(k, X, y)
    vals = [vfe_nlml_and_grad(th, k, X, y, X[:m])[0] for m in (10, 40, 120, 200)]
    assert all(a >= b - 1e-9 for a, b in itertools.pairwise(vals))


def test_fit_vfe_recovers_noise_on_1d_toy():
    rng = np.random.default_rng(4)
    N, noise_sd = 2000, 0.1
    X = np.sort(rng.uniform(-3.0, 3.0, N))[:, None]
    f_true = np.sin(2.0 * X[:, 0])
    y = f_true + noise_sd * rng.normal(size=N)
    Z = choose_inducing(X, 30, seed=0)
    k = make_kernel("matern32+cubic")
    t0 = time.perf_counter()
    res = fit_vfe(k, X, y, Z, warm_start_rows=None)  # the plain ml2.initial_theta start
    secs = time.perf_counter() - t0
    s2 = float(np.exp(res.theta[-1]))
    print(f"\nfit_vfe 1-D toy N={N} M=30: s2={s2:.5f} (true {noise_sd**2:.5f}), -F={res.nlml:.2f}, "
          f"iters={res.restarts}, {secs:.2f} s")
    assert isinstance(res, MLIIResult)
    assert np.allclose(k.get_theta(), res.theta[:-1])
    assert 0.8 * noise_sd**2 < s2 < 1.25 * noise_sd**2
    # at the optimum the bound is tight: close to the exact NLML at the same hyperparameters
    exact, _ = nlml_and_grad(res.theta, k, X, y)
    print(f"  -F={res.nlml:.3f} vs exact NLML {exact:.3f} (gap {res.nlml - exact:.3f} nats)")
    assert exact - 1e-6 <= res.nlml < exact + 0.01 * abs(exact)
    post = SparsePosterior.fit(k, s2, X, y, Z)
    Xs = np.linspace(-2.9, 2.9, 300)[:, None]
    mean, var = post.predict(Xs)
    rmse = float(np.sqrt(np.mean((mean - np.sin(2.0 * Xs[:, 0])) ** 2)))
    print(f"  sparse posterior RMSE vs truth: {rmse:.4f}, mean latent std {np.mean(np.sqrt(var)):.4f}")
    assert rmse < 0.03
    assert np.all(var > 0) and np.mean(np.sqrt(var)) < 0.05


def test_fit_vfe_on_narx_regressors_avoids_noise_only_optimum(sdof_data):
    """32-D NARX regressors of a noisy SDOF: from the data-scaled start alone L-BFGS-B slides to
    s2 -> var(y); the exact-ML-II warm start on a strided subset keeps the real optimum."""
    from gpnarx.model.regressors import stack_regressors
    from gpnarx.model.scaling import Standardizer

    X, Y, _ = stack_regressors([(sdof_data["u"], sdof_data["yn"])], 16, 16)
    X2, Y2, _ = stack_regressors([(sdof_data["u2"], sdof_data["y2"])], 16, 16)
    xs = Standardizer().fit(X)
    ym, ysd = Y.mean(), Y.std()
    Xs, Ys = xs.transform(X), (Y - ym) / ysd
    noise_true = (0.05 * np.std(sdof_data["y"]) / ysd) ** 2
    Z = choose_inducing(Xs, 64, seed=0)
    k = make_kernel("matern32+cubic")
    res = fit_vfe(k, Xs, Ys, Z, warm_start_rows=400)
    s2 = float(np.exp(res.theta[-1]))
    mean, _ = SparsePosterior.fit(k, s2, Xs, Ys, Z).predict(xs.transform(X2))
    nrmse = float(np.sqrt(np.mean((mean * ysd + ym - Y2) ** 2)) / np.std(Y2))
    print(f"\nSDOF NARX N={Xs.shape[0]} D=32 M=64: starts {res.restarts}, s2={s2:.4g} (true {noise_true:.4g}), "
          f"one-step NRMSE {nrmse:.4f}, {res.seconds:.2f} s")
    assert len(res.restarts) == 2
    assert 0.5 * noise_true < s2 < 2.0 * noise_true
    assert nrmse < 0.02
    # theta0 given: only that start is used
    res0 = fit_vfe(k, Xs, Ys, Z, theta0=res.theta, max_iter=5)
    assert len(res0.restarts) == 1 and res0.nlml <= res.nlml + 1e-6


def test_timing_printout_vfe_vs_exact():
    rng = np.random.default_rng(5)
    N, D, M = 4000, 37, 256
    X = rng.normal(size=(N, D))
    y = np.tanh(X[:, 0]) + 0.1 * X[:, 1] * X[:, 2] + 0.05 * rng.normal(size=N)
    y -= y.mean()
    k = make_kernel("matern32+cubic")
    th = initial_theta(k, X, y)
    Z = X[rng.choice(N, M, replace=False)]  # cost per evaluation does not depend on how Z was chosen
    vfe_nlml_and_grad(th, k, X, y, Z)  # warm-up
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        fv, gv = vfe_nlml_and_grad(th, k, X, y, Z)
    t_vfe = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    fe, _ = nlml_and_grad(th, k, X, y)
    t_exact = time.perf_counter() - t0
    print(f"\n[1 BLAS thread] N={N} D={D} M={M}: VFE bound+grad {t_vfe * 1e3:.1f} ms/eval, exact nlml_and_grad "
          f"{t_exact * 1e3:.1f} ms/eval (x{t_exact / t_vfe:.1f}); "
          f"-F={fv:.2f} >= NLML={fe:.2f}")
    assert np.isfinite(fv) and np.all(np.isfinite(gv))
    assert fv >= fe - 1e-8 * abs(fe)
