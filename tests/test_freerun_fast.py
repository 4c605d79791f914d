"""The fast free-run paths agree with their reference implementations.

* ``linear.simulate_linear`` (mean recursion, batched eq. 9 and gradients, covariance recursion) gives the
  numbers of the stepwise run (``reference.simulate_linear_reference``: one ``mean_grad`` per step), sparse and
  exact posteriors.
* ``mc.simulate_mc`` (checked local model per step) gives, with the same seed, the bands of
  ``reference.simulate_mc_reference`` up to far less than their Monte Carlo error; ``local=False`` and a
  check that always fails give the reference's numbers.
* The kernels' batched gradient and second-order terms match finite differences.
* ``GPNARX.simulate`` is ``freerun.run`` on the model's ``Predictor`` and a ``RunSpec``, through the runner table.
"""
import numpy as np
import pytest

from gpnarx.model import freerun
from gpnarx.model.estimator import GPNARX
from gpnarx.model.freerun import linear, mc, reference
from gpnarx.model.kernels import RBF, CubicPolynomial, Matern32, Sum, White
from gpnarx.model.kernels.base import _r2_from_gram

THETA = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])


@pytest.fixture(scope="module")
def sparse_model(sdof_data):
    return GPNARX(ny=6, nu=6, mode="sparse", n_inducing=64, max_train_points=400).fit(
        [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=THETA)


@pytest.fixture(scope="module")
def exact_model(sdof_data):
    return GPNARX(ny=6, nu=6, mode="exact", max_train_points=300).fit(
        [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=THETA)


def _args(m, u):
    return (m.posterior_, m.x_scaler_, m.y_scaler_, m.ny, m.nu, u)


@pytest.mark.parametrize("which", ["sparse", "exact"])
@pytest.mark.parametrize("kw", [{}, {"y0": "measured"}, {"cov_window": 15}])
def test_linear_matches_reference(which, kw, sparse_model, exact_model, sdof_data):
    m = sparse_model if which == "sparse" else exact_model
    u = sdof_data["u2"][:600]
    kw = dict(kw)
    if kw.get("y0") == "measured":
        kw["y0"] = sdof_data["y2"][:6]
    new = linear.simulate_linear(*_args(m, u), **kw)
    ref = reference.simulate_linear_reference(*_args(m, u), **kw)
    scale = np.abs(ref.mean).max()
    assert np.allclose(new.mean, ref.mean, rtol=0, atol=1e-9 * scale)
    assert np.allclose(new.std, ref.std, rtol=1e-7, atol=1e-12 * scale)
    assert np.allclose(new.upper, ref.upper, rtol=0, atol=1e-9 * scale)
    assert np.allclose(new.latent_upper, ref.latent_upper, rtol=0, atol=1e-9 * scale)
    assert np.allclose(new.latent_lower, ref.latent_lower, rtol=0, atol=1e-9 * scale)
    if "cov_window" in kw:
        assert new.cov_band.shape == ref.cov_band.shape == (u.size, 15)
        assert np.allclose(new.cov_band, ref.cov_band, rtol=1e-7, atol=1e-12 * scale ** 2)
    assert new.path_steps == ref.path_steps and new.method == "linear"


def test_mc_local_matches_reference_same_seed(sparse_model, sdof_data):
    m = sparse_model
    u = sdof_data["u2"][:400]
    new = mc.simulate_mc(*_args(m, u), n_paths=256, seed=3)
    ref = reference.simulate_mc_reference(*_args(m, u), n_paths=256, seed=3)
    other = reference.simulate_mc_reference(*_args(m, u), n_paths=256, seed=4)
    assert new.local_steps > 0.9 * u.size  # the local model served (nearly) every step
    # Monte Carlo standard error of the band edges, from the reference at two seeds
    se = np.median(np.abs(np.r_[ref.lower - other.lower, ref.upper - other.upper])) / np.sqrt(2)
    assert se > 0
    # same draws: the product's bands differ from the reference's by far less than that error
    assert np.max(np.abs(new.lower - ref.lower)) < 0.1 * se
    assert np.max(np.abs(new.upper - ref.upper)) < 0.1 * se
    assert np.max(np.abs(new.mean - ref.mean)) < 0.1 * se
    assert np.max(np.abs(new.latent_upper - ref.latent_upper)) < 0.1 * se
    y = sdof_data["y2"][:400]
    cov = [100 * np.mean((y >= r.lower) & (y <= r.upper)) for r in (new, ref)]
    assert abs(cov[0] - cov[1]) < 1.0


def test_mc_exact_paths_equal_reference(sparse_model, sdof_data, monkeypatch):
    m = sparse_model
    u = sdof_data["u2"][:120]
    ref = reference.simulate_mc_reference(*_args(m, u), n_paths=128, seed=1)
    off = mc.simulate_mc(*_args(m, u), n_paths=128, seed=1, local=False)
    assert off.local_steps == 0
    assert np.array_equal(off.mean, ref.mean) and np.array_equal(off.upper, ref.upper)
    assert np.array_equal(off.latent_lower, ref.latent_lower)
    est = m.simulate(u, n_paths=128, seed=1, local=False)  # GPNARX.simulate passes local= through
    assert est.local_steps == 0 and np.array_equal(est.mean, ref.mean) and np.array_equal(est.upper, ref.upper)
    monkeypatch.setattr(mc, "LOCAL_TOL_MEAN", -1.0)  # every check fails: every step exact
    failed = mc.simulate_mc(*_args(m, u), n_paths=128, seed=1)
    assert failed.local_steps == 0
    assert np.array_equal(failed.mean, ref.mean) and np.array_equal(failed.lower, ref.lower)


def test_mc_few_paths_and_measured_start(sparse_model, sdof_data):
    m = sparse_model
    u = sdof_data["u2"][:100]
    few = mc.simulate_mc(*_args(m, u), n_paths=16, seed=0)
    assert few.local_steps == 0  # below LOCAL_MIN_PATHS: exact
    y0 = sdof_data["y2"][:6]
    a = mc.simulate_mc(*_args(m, u), n_paths=128, seed=0, y0=y0)
    b = reference.simulate_mc_reference(*_args(m, u), n_paths=128, seed=0, y0=y0)
    assert np.array_equal(a.mean[:6], b.mean[:6])
    assert np.allclose(a.upper, b.upper, rtol=0, atol=1e-3 * np.abs(b.upper).max())


KERNELS = [RBF(0.7, 1.3), Matern32(0.5, 2.0), CubicPolynomial(0.3, 0.2, 1.5, constant_cap=1.0), White(0.1),
           Sum(Matern32(0.5, 2.0), CubicPolynomial(0.1, 0.1, 2.0, constant_cap=1.0))]


@pytest.mark.parametrize("k", KERNELS, ids=lambda k: type(k).__name__)
def test_kernel_batched_gradient_and_local_terms(k):
    rng = np.random.default_rng(0)
    D, ny = 6, 3
    Z = rng.normal(size=(30, D))
    Xs = rng.normal(size=(5, D))
    w = rng.normal(size=30)
    ref = np.stack([k.grad_x(x, Z).T @ w for x in Xs])
    assert np.allclose(k.grad_dot(Xs, Z, w), ref, rtol=1e-10, atol=1e-12)
    G = Xs @ Z.T
    K, g = k.value_and_grad_dot(Xs, Z, w, G, np.einsum("ij,ij->i", Xs, Xs), np.einsum("ij,ij->i", Z, Z))
    assert np.allclose(K, k.cross(Xs, Z), rtol=1e-12, atol=1e-14) and np.allclose(g, ref, rtol=1e-10, atol=1e-12)
    x = Xs[0]
    kv, J, hess = k.local_terms(x, Z, ny)
    assert np.allclose(kv, k.cross(x[None], Z)[0])
    h = 1e-4
    E = np.eye(D)
    Jfd = np.stack([(k.cross((x + h * E[j])[None], Z)[0] - k.cross((x - h * E[j])[None], Z)[0]) / (2 * h)
                    for j in range(ny)], 1)
    assert np.allclose(J, Jfd, rtol=1e-6, atol=1e-8)

    def f(xx):
        return k.cross(xx[None], Z)[0] @ w

    Hfd = np.array([[(f(x + h * (E[i] + E[j])) - f(x + h * (E[i] - E[j])) - f(x - h * (E[i] - E[j]))
                      + f(x - h * (E[i] + E[j]))) / (4 * h * h) for j in range(ny)] for i in range(ny)])
    assert np.allclose(hess(w), Hfd, rtol=1e-4, atol=1e-6)
    d0, dg, dH = k.diag_local(x, ny)
    assert d0 == pytest.approx(float(k.diag(x[None])[0]))
    dgfd = np.array([(k.diag((x + h * E[j])[None])[0] - k.diag((x - h * E[j])[None])[0]) / (2 * h)
                     for j in range(ny)])
    assert np.allclose(dg, dgfd, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("k", KERNELS, ids=lambda k: type(k).__name__)
def test_kernel_local_profile_gives_local_terms(k):
    rng = np.random.default_rng(1)
    D, ny = 6, 3
    Z = rng.normal(size=(30, D))
    Xa = rng.normal(size=(4, D))  # the expansion point and three other rows
    G = Xa @ Z.T
    sq = np.einsum("ij,ij->i", Xa, Xa)
    prof = k.local_profile(_r2_from_gram(G, sq, np.einsum("ij,ij->i", Z, Z)), G, sq)
    assert np.allclose(prof.k, k.cross(Xa, Z), rtol=1e-12, atol=1e-14)
    assert np.allclose(prof.kd, k.diag(Xa), rtol=1e-12, atol=1e-14)
    x = Xa[0]
    kv, J, hess = k.local_terms(x, Z, ny)
    Dy, Zy = x[:ny] - Z[:, :ny], Z[:, :ny]
    zero = np.zeros(Z.shape[0])
    a, b, p, q, t = (zero if v is None else v for v in (prof.a, prof.b, prof.p, prof.q, prof.t))
    assert np.allclose(a[:, None] * Dy + b[:, None] * Zy, J, rtol=1e-10, atol=1e-14)
    w = rng.normal(size=Z.shape[0])
    H = Dy.T @ ((w * p)[:, None] * Dy) + (w @ q) * np.eye(ny) + Zy.T @ ((w * t)[:, None] * Zy)
    assert np.allclose(H, hess(w), rtol=1e-10, atol=1e-14)
    d0, dg, dH = k.diag_local(x, ny)
    xy = x[:ny]
    assert prof.kd[0] == pytest.approx(d0, rel=1e-14)
    assert np.allclose(prof.dg * xy, dg, rtol=1e-12, atol=1e-14)
    assert np.allclose(prof.dH * np.outer(xy, xy) + prof.dI * np.eye(ny), dH, rtol=1e-12, atol=1e-14)


class _NoProfile(Matern32):
    def local_profile(self, r2, g, sq):
        return None


@pytest.mark.parametrize("fused", [True, False])
def test_fused_local_model_matches_local_model(sparse_model, exact_model, fused):
    from gpnarx.model.freerun.mc_local import LocalModel, local_model

    for m in (sparse_model, exact_model):
        post = m.posterior_
        lm = LocalModel(post, m.ny)
        if not fused:
            lm.kernel = _NoProfile(1.0, 1.0)
            lm.fused = False
        x = post.points[3] + 0.01
        Xc = post.points[:5] + 0.02
        H, mean_c, var_c = lm(x, Xc)
        t = local_model(post, x, m.ny, Xc)
        ny, a = m.ny, m.ny + 1
        rng = np.random.default_rng(0)
        d = np.c_[0.05 * rng.normal(size=(7, ny)), np.ones(7)]
        mu = np.einsum("ij,jk,ik->i", d, H[:, :a], d)
        var = np.einsum("ij,jk,ik->i", d, H[:, a:], d)
        dy = d[:, :ny]
        mu0 = t.m0 + dy @ t.gm + 0.5 * np.einsum("ij,jk,ik->i", dy, t.Hm, dy)
        var0 = t.v0 + dy @ t.gv + 0.5 * np.einsum("ij,jk,ik->i", dy, t.Hv, dy)
        assert np.allclose(mu, mu0, rtol=1e-9, atol=1e-12)
        assert np.allclose(var, var0, rtol=1e-6, atol=1e-6 * abs(t.v0))
        assert np.allclose(mean_c, t.mean_c, rtol=1e-9, atol=1e-12) and np.allclose(var_c, t.var_c, rtol=1e-6)


def test_local_model_matches_posterior_at_its_centre(sparse_model, exact_model):
    from gpnarx.model.freerun.mc_local import local_model

    for m in (sparse_model, exact_model):
        post = m.posterior_
        x = post.points[3] + 0.01
        Xc = post.points[:4] + 0.02
        t = local_model(post, x, m.ny, Xc)
        mu, var = post.predict(np.vstack([x, Xc]))
        assert t.m0 == pytest.approx(mu[0], rel=1e-9, abs=1e-12)
        assert t.v0 == pytest.approx(var[0], rel=1e-6)
        assert np.allclose(t.mean_c, mu[1:], rtol=1e-9, atol=1e-12) and np.allclose(t.var_c, var[1:], rtol=1e-6)
        _, _, g = post.mean_var_grad(x[None])
        assert np.allclose(t.gm, g[0, : m.ny], rtol=1e-8, atol=1e-12)


def test_linear_pass2_workers_give_the_same_numbers(exact_model, sdof_data):
    # pass 2 on worker threads while pass 1 runs (more than one chunk of steps): the serial run's numbers,
    # bit for bit, and the reference loop's to round-off
    m = exact_model
    u = sdof_data["u2"][: 2 * linear._PASS1_CHUNK + 300]
    runs = [linear.simulate_linear(*_args(m, u), workers=k, cov_window=9) for k in (0, 1, 2)]
    for r in runs[1:]:
        for a in ("mean", "std", "lower", "upper", "latent_lower", "latent_upper", "cov_band"):
            assert np.array_equal(getattr(r, a), getattr(runs[0], a)), a
    ref = reference.simulate_linear_reference(*_args(m, u), cov_window=9)
    scale = np.abs(ref.mean).max()
    assert np.allclose(runs[1].mean, ref.mean, rtol=0, atol=1e-9 * scale)
    assert np.allclose(runs[1].std, ref.std, rtol=1e-7, atol=1e-12 * scale)
    with pytest.raises(ValueError, match="workers"):
        linear.simulate_linear(*_args(m, u), workers=-1)


def test_linear_pass2_worker_error_reaches_the_caller(exact_model, sdof_data):
    m = exact_model

    class Failing(type(m.posterior_)):
        def mean_var_grad(self, Xs, block=256):
            raise FloatingPointError("pass 2 failed")

    post = m.posterior_
    bad = Failing(post.kernel, post.noise_var, post.X_train, post.alpha, post.Linv)
    u = sdof_data["u2"][: linear._PASS1_CHUNK + 50]
    with pytest.raises(FloatingPointError, match="pass 2 failed"):
        linear.simulate_linear(bad, m.x_scaler_, m.y_scaler_, m.ny, m.nu, u, workers=1)


def test_lower_times_rows_and_triangular_local_model(exact_model, monkeypatch):
    from scipy.linalg import blas
    from threadpoolctl import threadpool_limits

    from gpnarx.model import linalg
    from gpnarx.model.freerun import mc_local
    from gpnarx.model.freerun.mc_local import LocalModel
    from gpnarx.model.linalg import lower_times_rows

    rng = np.random.default_rng(3)
    L = np.tril(rng.normal(size=(90, 90)))
    K = rng.normal(size=(21, 90))
    want = blas.dtrmm(1.0, L.T, np.ascontiguousarray(K).T, side=0, lower=0, trans_a=1).T
    assert np.array_equal(lower_times_rows(L, K), want)  # the same BLAS routine, without the GIL
    # rows in two halves: BLAS may block a smaller product otherwise, so the same rows to round-off
    assert np.allclose(lower_times_rows(L, K, split=True), want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
    assert np.allclose(want, K @ L.T, rtol=1e-12, atol=1e-12 * np.abs(K @ L.T).max())
    assert np.allclose(lower_times_rows(L, K, transpose=True), K @ L, rtol=1e-12, atol=1e-12 * np.abs(K @ L).max())
    # the local model's pair F [k | ...] and F^T F k: split over the helper thread (two CPUs) or in one thread
    back_want = L.T @ (L @ K[0])
    for two in (True, False):
        monkeypatch.setattr(linalg, "_two_threads", lambda two=two: two)
        for rows in (1, 7, 21, 29):
            FB, back = linalg.lower_times_rows_and_back(L, K[:rows] if rows <= 21 else np.vstack([K, K[:8]]))
            ref = want[:rows] if rows <= 21 else np.vstack([want, want[:8]])
            assert np.allclose(FB, ref, rtol=1e-13, atol=1e-13 * np.abs(ref).max())
            assert np.allclose(back, back_want, rtol=1e-12, atol=1e-12 * np.abs(back_want).max())
    monkeypatch.undo()
    # the exact posterior's lower-triangular factor takes dtrmm in the local model: the dense product's numbers
    post = exact_model.posterior_
    tri, dense = LocalModel(post, exact_model.ny), LocalModel(post, exact_model.ny)
    assert tri.F_lower
    dense.F_lower = False
    x = post.points[3] + 0.01
    Xc = post.points[:5] + 0.02
    calls = []
    pair = mc_local.lower_times_rows_and_back
    monkeypatch.setattr(mc_local, "lower_times_rows_and_back", lambda *a: calls.append(a) or pair(*a))
    with threadpool_limits(limits=1, user_api="blas"):
        assert linalg.blas_threads() == 1
        (Ht, mt, vt), (Hd, md, vd) = tri(x, Xc), dense(x, Xc)
    assert len(calls) == 1  # F B and F^T (F k) by dtrmm on one BLAS thread
    assert np.allclose(Ht, Hd, rtol=1e-9, atol=1e-12 * np.abs(Hd).max())
    assert np.allclose(mt, md, rtol=1e-9, atol=1e-12) and np.allclose(vt, vd, rtol=1e-9)
    # with a multi-threaded BLAS, numpy's dense product (scipy's and numpy's thread pools would take the cores
    # from each other): no dtrmm, the same numbers
    calls.clear()
    with threadpool_limits(limits=2, user_api="blas"):
        assert linalg.blas_threads() == 2
        H2, m2, v2 = tri(x, Xc)
    assert not calls
    assert np.allclose(H2, Ht, rtol=1e-9, atol=1e-12 * np.abs(Ht).max())
    assert np.allclose(m2, mt, rtol=1e-9, atol=1e-12) and np.allclose(v2, vt, rtol=1e-9)


@pytest.mark.parametrize("n", [0, 1, 2])
def test_workers_follow_each_task_in_submission_order(n):
    """``linear._Workers``' ``then`` (the linearised run's pass 3) runs on the calling thread, after ``fn`` has
    finished each task, in the order the tasks were submitted, however the workers finish them."""
    import threading
    import time

    events = []
    lock = threading.Lock()
    delays = np.random.default_rng(n).uniform(0, 0.004, 24)

    def fn(k):
        time.sleep(delays[k])
        with lock:
            events.append(("fn", k))

    def then(k):
        assert threading.current_thread() is threading.main_thread()
        with lock:
            events.append(("then", k))

    with linear._Workers(fn, n, then=then) as pool:
        for k in range(24):
            pool.submit(k)
            time.sleep(0.001)
    follows = [k for kind, k in events if kind == "then"]
    assert follows == list(range(24))
    assert all(events.index(("fn", k)) < events.index(("then", k)) for k in range(24))


def test_workers_stop_following_at_a_failed_task():
    """A task that raises: its error is raised on leaving the block, and no task from it on is followed."""
    followed = []

    def fn(k):
        if k == 5:
            raise FloatingPointError("task 5")

    with pytest.raises(FloatingPointError, match="task 5"):
        with linear._Workers(fn, 1, then=followed.append) as pool:
            for k in range(12):
                pool.submit(k)
    assert followed == list(range(len(followed))) and len(followed) <= 5


def test_workers_stop_when_the_follow_up_raises():
    """``then`` raising on the calling thread: its error comes out of the block and the worker threads end."""
    import threading

    def then(k):
        if k == 3:
            raise ValueError("follow-up 3")

    before = threading.active_count()
    with pytest.raises(ValueError, match="follow-up 3"):
        with linear._Workers(lambda k: None, 2, then=then) as pool:
            for k in range(10):
                pool.submit(k)
    assert threading.active_count() == before


def test_simulate_is_the_runner_of_its_method_and_backend(sparse_model, sdof_data, monkeypatch):
    """``GPNARX.simulate`` hands the model's ``Predictor`` and a ``RunSpec`` to ``freerun.run``, which calls the
    runner of (method, backend) in ``RUNNERS``: the same numbers bit for bit; a new entry is all a new method needs."""
    from gpnarx.model.freerun import Predictor, RunSpec

    m = sparse_model
    u = sdof_data["u2"][:200]
    assert set(freerun.RUNNERS) == {("mc", "numpy"), ("linear", "numpy"), ("mc", "jax"), ("linear", "jax")}
    assert freerun.METHODS == ("mc", "linear")
    pred = m.predictor()
    assert isinstance(pred, Predictor) and (pred.ny, pred.nu) == (m.ny, m.nu) and pred.posterior is m.posterior_
    for method in freerun.METHODS:
        spec = RunSpec(method=method, n_paths=96, seed=4, confidence=0.9, y0=sdof_data["y2"][:6],
                       include_noise=m.include_noise)
        a, b = m.simulate(u, method=method, n_paths=96, seed=4, confidence=0.9, y0=sdof_data["y2"][:6]), \
            freerun.run(pred, u, spec)
        for k in ("mean", "std", "lower", "upper", "latent_lower", "latent_upper"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), (method, k)
    # the functional form: the predictor's parts and the spec's fields as keywords, the same run
    c = freerun.simulate_mc(m.posterior_, m.x_scaler_, m.y_scaler_, m.ny, m.nu, u, n_paths=96, seed=4)
    d = freerun.run_mc(Predictor.of(m.posterior_, m.x_scaler_, m.y_scaler_, m.ny, m.nu), u,
                       RunSpec(n_paths=96, seed=4))
    assert np.array_equal(c.upper, d.upper) and np.array_equal(c.mean, d.mean)
    with pytest.raises(ValueError, match="method must be 'mc' or 'linear', got 'taylor2'"):
        freerun.run(pred, u, RunSpec(method="taylor2"))
    with pytest.raises(ValueError, match="method must be 'mc' or 'linear'"):
        m.simulate(u, method="taylor2")
    with pytest.raises(ValueError, match="runs on backend 'numpy' or 'jax', got 'torch'"):
        freerun.run(pred, u, RunSpec(method="linear", backend="torch"))
    seen = []
    monkeypatch.setitem(freerun.RUNNERS, ("linear", "numpy"), lambda p, uu, s: seen.append((p, s.cov_window)) or "ran")
    assert m.simulate(u, method="linear", cov_window=9) == "ran" and seen[0][1] == 9


def test_linear_runs_stepwise_without_mean_terms_and_loads_no_baseline(exact_model, sdof_data):
    """A posterior the three-pass run cannot take (only ``mean_grad`` and ``noise_var``) runs stepwise
    (``linear_stepwise``), bit for bit; the product's modules import neither the tests' reference nor JAX."""
    import subprocess
    import sys

    from gpnarx.model.freerun import Predictor, RunSpec
    from gpnarx.model.freerun.linear_stepwise import run_linear_stepwise

    m = exact_model

    class MeanGradOnly:
        noise_var = m.posterior_.noise_var

        def mean_grad(self, x):
            return m.posterior_.mean_grad(x)

    u = sdof_data["u2"][:150]
    a = linear.simulate_linear(MeanGradOnly(), m.x_scaler_, m.y_scaler_, m.ny, m.nu, u, cov_window=8)
    b = run_linear_stepwise(Predictor.of(MeanGradOnly(), m.x_scaler_, m.y_scaler_, m.ny, m.nu), u,
                            RunSpec(method="linear", cov_window=8))
    assert np.array_equal(a.std, b.std) and np.array_equal(a.cov_band, b.cov_band)
    code = ("import sys, numpy as np; from gpnarx.model.estimator import GPNARX; u = np.sin(np.arange(300) / 7); "
            "m = GPNARX(ny=2, nu=2, max_train_points=100, n_restarts=0).fit([(u, np.roll(u, 1))]); "
            "m.simulate(u[:50], method='linear'); m.simulate(u[:50], n_paths=64); "
            "print(sorted(k for k in sys.modules if k.endswith(('freerun.reference', 'freerun.jax_backend')) "
            "or k == 'jax'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
