"""The JAX backend (issue 35) on CPU: the same answers as the numpy backend, within Monte Carlo error for
Monte Carlo runs and to rounding for everything deterministic (kernels, linearised runs, ML-II, solves),
and clear errors for a backend that is unknown or not installed. CI has no GPU: this is the code path a GPU
runs, compiled for the CPU."""
import json
import sys

import numpy as np
import pytest

pytest.importorskip("jax", reason="the 'jax' extra is part of the test install (.ci/run)")

from gpnarx.model import backend as B  # noqa: E402
from gpnarx.model.estimator import GPNARX  # noqa: E402
from gpnarx.model.kernels import RBF, CubicPolynomial, Matern32, Sum, White  # noqa: E402
from gpnarx.model.kernels.jax_forms import jax_kernel, kernel_theta  # noqa: E402


def duffing(u, fs=500.0):
    """A softening-hardening SDOF (Duffing, m = 1 kg, 12 Hz, 3 % damping), semi-implicit Euler [m]."""
    wn, z, k3, dt = 2 * np.pi * 12.0, 0.03, 4e6, 1.0 / fs
    x = v = 0.0
    y = np.empty(u.size)
    for i, ui in enumerate(u):
        a = ui - 2 * z * wn * v - wn * wn * x - k3 * x**3
        v += dt * a
        x += dt * v
        y[i] = x
    return y


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(3)
    u = 40.0 * rng.standard_normal(2400)
    y = duffing(u)
    y = y + 0.02 * np.std(y) * rng.standard_normal(y.size)
    u2 = 40.0 * rng.standard_normal(600)
    return {"train": [(u[:1600], y[:1600])], "held": [(u[1600:], y[1600:])], "u2": u2, "y2": duffing(u2)}


@pytest.fixture(scope="module")
def sparse_model(data):
    return GPNARX(ny=4, nu=4, mode="sparse", n_inducing=48, max_train_points=400, n_restarts=0).fit(data["train"])


@pytest.fixture(scope="module")
def exact_model(data):
    return GPNARX(ny=4, nu=4, mode="exact", max_train_points=300, n_restarts=0).fit(data["train"])


KERNELS = [Matern32(0.7, 1.3), RBF(1.2, 0.8), CubicPolynomial(0.05, 0.3, 2.0),
           CubicPolynomial(0.05, 0.3, 20.0, constant_cap=10.0), White(0.01),
           Sum(Matern32(0.9, 2.0), CubicPolynomial(0.01, 0.5, 30.0, constant_cap=5.0)), Sum(RBF(), White(1e-3))]


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: repr(k)[:40])
def test_every_kernel_has_the_same_formula_in_jax(kernel):
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    X1, X2 = rng.standard_normal((7, 5)), rng.standard_normal((9, 5))
    jk, th = jax_kernel(kernel), jnp.asarray(kernel_theta(kernel))
    sq1, sq2 = np.einsum("ij,ij->i", X1, X1), np.einsum("ij,ij->i", X2, X2)
    K = np.asarray(jk.cross(th, jnp.asarray(X1 @ X2.T), jnp.asarray(sq1), jnp.asarray(sq2)))
    np.testing.assert_allclose(K, kernel.cross(X1, X2), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(jk.diag(th, jnp.asarray(sq1))), kernel.diag(X1), rtol=1e-12)
    # a training covariance: the white parts only on the diagonal
    Kxx = np.asarray(jk.cross(th, jnp.asarray(X1 @ X1.T), jnp.asarray(sq1), jnp.asarray(sq1)))
    Kxx = Kxx + float(jk.white(th)) * np.eye(7)
    np.testing.assert_allclose(Kxx, kernel(X1), rtol=1e-10, atol=1e-12)


def test_a_kernel_without_a_jax_form_says_so():
    from gpnarx.model.kernels import Kernel

    class Odd(Kernel):  # the core contract alone: no family base, no Kernel.jax_part
        param_names = ("variance",)

        def from_gram(self, G, sq1, sq2):
            return np.exp(self.theta[0]) * G

    with pytest.raises(NotImplementedError, match="Odd has no JAX form"):
        jax_kernel(Odd() + RBF())

    class Even(RBF):  # a family's subclass has its formula, so its JAX form
        pass

    assert jax_kernel(Even()).n_params == 2


@pytest.mark.parametrize("which", ["sparse", "exact"])
def test_linearised_run_on_jax_is_the_numpy_run(which, sparse_model, exact_model, data):
    m = sparse_model if which == "sparse" else exact_model
    u = data["u2"]
    for kw in ({}, {"y0": data["y2"][:6], "cov_window": 9}):
        a = m.simulate(u, method="linear", backend="numpy", **kw)
        b = m.simulate(u, method="linear", backend="jax", **kw)
        assert b.backend == "jax" and a.backend == "numpy" and b.method == "linear"
        scale = float(np.max(np.abs(a.mean)))
        np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(b.std, a.std, rtol=1e-7, atol=1e-12 * scale)
        np.testing.assert_allclose(b.latent_upper, a.latent_upper, rtol=0, atol=1e-9 * scale)
        if kw:
            assert np.array_equal(b.mean[:4], data["y2"][:4])  # y0 holds its first ny samples
            np.testing.assert_allclose(b.cov_band, a.cov_band, rtol=1e-6, atol=1e-12 * scale**2)


def _edge_gap(a, b):
    """Median |difference| of two runs' band edges and the largest |difference| of their means."""
    return (float(np.median(np.abs(np.concatenate([a.lower - b.lower, a.upper - b.upper])))),
            float(np.max(np.abs(a.mean - b.mean))))


def test_monte_carlo_on_jax_agrees_with_numpy_within_monte_carlo_error(sparse_model, data):
    m, u, P = sparse_model, data["u2"][:300], 512
    np0 = m.simulate(u, n_paths=P, seed=0, backend="numpy")
    np1 = m.simulate(u, n_paths=P, seed=1, backend="numpy")
    jx0 = m.simulate(u, n_paths=P, seed=0, backend="jax")
    same_backend, cross = _edge_gap(np0, np1), _edge_gap(jx0, np0)
    # the backends differ by no more than two runs of one backend at different seeds do
    assert cross[0] <= 1.5 * same_backend[0], (cross, same_backend)
    assert cross[1] <= 3.0 * same_backend[1] + 1e-12, (cross, same_backend)
    assert jx0.n_paths == P and jx0.method == "mc" and jx0.backend == "jax" and jx0.path_steps == 300 * P
    assert np.all(jx0.lower <= jx0.mean) and np.all(jx0.mean <= jx0.upper)
    # the latent band (no noise term at the reported step) is the narrower one
    assert np.mean(jx0.latent_upper - jx0.latent_lower) < np.mean(jx0.upper - jx0.lower)
    assert jx0.diverged_paths == 0
    # seeded: the same seed gives the same run, another seed another
    again = m.simulate(u, n_paths=P, seed=0, backend="jax")
    assert np.array_equal(again.upper, jx0.upper)
    assert not np.array_equal(m.simulate(u, n_paths=P, seed=1, backend="jax").upper, jx0.upper)


def test_monte_carlo_on_jax_keeps_paths_starts_from_measured_outputs_and_counts_divergence(exact_model, data):
    m, u = exact_model, data["u2"][:120]
    y0 = data["y2"][:4]
    run = m.simulate(u, n_paths=64, seed=2, y0=y0, keep_paths=True, backend="jax", confidence=0.9)
    assert run.paths.shape == (120, 64) and np.all(run.paths[:4] == y0[:, None])
    assert np.array_equal(run.mean[:4], y0) and run.confidence == 0.9
    # the band is the quantiles of the kept paths
    np.testing.assert_allclose(run.upper[4:], np.quantile(run.paths[4:], 0.95, axis=1), rtol=1e-12)
    np.testing.assert_allclose(run.std[4:], np.std(run.paths[4:], axis=1), rtol=1e-12)
    # a drive 1000x the training's leaves the envelope: every path passes the divergence limit
    far = m.simulate(1000.0 * u, n_paths=16, seed=0, backend="jax")
    near = m.simulate(1000.0 * u, n_paths=16, seed=0, backend="numpy")
    assert far.diverged_paths == near.diverged_paths == 16
    assert np.all(np.isfinite(far.mean)) and np.all(np.isfinite(far.upper))


def test_float32_on_jax_stays_close_where_the_variance_is_well_resolved(sparse_model, data):
    u = data["u2"][:200]
    a = sparse_model.simulate(u, n_paths=256, seed=0, backend="jax")
    b = sparse_model.simulate(u, n_paths=256, seed=0, backend="jax", float32=True)
    scale = float(np.max(a.upper - a.lower))
    assert float(np.max(np.abs(b.mean - a.mean))) < 0.05 * scale


def test_ml2_and_exact_solves_on_jax_match_numpy(data):
    from gpnarx.model.gp import ExactPosterior
    from gpnarx.model.kernels import make_kernel
    from gpnarx.model.ml2 import NLMLWorkspace, fit_ml2, initial_theta, nlml_and_grad
    from gpnarx.model.ml2_jax import nlml_and_grad_jax, predict_exact_jax

    rng = np.random.default_rng(1)
    X = rng.standard_normal((250, 6))
    y = np.sin(X[:, 0]) + 0.1 * X[:, 1] ** 3 + 0.05 * rng.standard_normal(250)
    k = make_kernel("matern32+cubic")
    th = initial_theta(k, X, y) + 0.2
    v0, g0 = nlml_and_grad(th, k, X, y, NLMLWorkspace(k, X))
    v1, g1 = nlml_and_grad_jax(th, k, X, y)
    assert v1 == pytest.approx(v0, rel=1e-10) and np.allclose(g1, g0, rtol=1e-8, atol=1e-8 * np.abs(g0).max())
    r0 = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0)
    k1 = make_kernel("matern32+cubic")
    r1 = fit_ml2(k1, X, y, n_restarts=0, backend="jax")
    assert r1.nlml == pytest.approx(r0.nlml, abs=1e-3)
    p0 = ExactPosterior.fit(k1, float(np.exp(r1.theta[-1])), X, y)
    p1 = ExactPosterior.fit(k1, float(np.exp(r1.theta[-1])), X, y, backend="jax")
    np.testing.assert_allclose(p1.alpha, p0.alpha, rtol=1e-7, atol=1e-9 * np.abs(p0.alpha).max())
    Xs = rng.standard_normal((40, 6))
    m0, s0 = p0.predict(Xs)
    m1, s1 = predict_exact_jax(p0, Xs, block=16)
    # round-off scaled to the means (a mean near zero differs by the sum's rounding, 1e-12 of its terms)
    np.testing.assert_allclose(m1, m0, rtol=1e-10, atol=1e-10 * np.abs(m0).max())
    np.testing.assert_allclose(s1, s0, rtol=1e-8, atol=1e-14)
    with pytest.raises(ValueError, match="backend must be 'numpy' or 'jax'"):
        fit_ml2(make_kernel("rbf"), X, y, backend="torch")


def test_an_exact_model_fitted_on_jax_is_the_numpy_fit(data):
    kw = dict(ny=4, nu=4, mode="exact", max_train_points=300, n_restarts=0)
    a = GPNARX(**kw).fit(data["train"], heldout=data["held"])
    b = GPNARX(**kw, fit_backend="jax").fit(data["train"], heldout=data["held"])
    assert b.nlml_ == pytest.approx(a.nlml_, abs=1e-3)
    assert b.noise_calibration_["noise_var"] == pytest.approx(a.noise_calibration_["noise_var"], rel=1e-2)
    ra, rb = a.simulate(data["u2"], method="linear"), b.simulate(data["u2"], method="linear")
    assert float(np.max(np.abs(ra.mean - rb.mean))) < 1e-3 * float(np.max(np.abs(ra.mean)))
    with pytest.raises(ValueError, match="fit_backend must be one of"):
        GPNARX(fit_backend="cuda").fit(data["train"])


def test_backend_choice_and_its_errors(sparse_model, data, monkeypatch):
    u = data["u2"][:50]
    with pytest.raises(ValueError, match=r"backend must be one of \['numpy', 'jax'\], got 'torch'"):
        sparse_model.simulate(u, backend="torch")
    monkeypatch.setenv("GPNARX_BACKEND", "jax")
    assert B.default_backend() == "jax"
    assert sparse_model.simulate(u, method="linear").backend == "jax"
    monkeypatch.setenv("GPNARX_BACKEND", "gpu")
    with pytest.raises(ValueError, match="GPNARX_BACKEND must be one of"):
        sparse_model.simulate(u, method="linear")
    monkeypatch.delenv("GPNARX_BACKEND")
    assert sparse_model.simulate(u, method="linear").backend == "numpy"
    monkeypatch.setitem(sys.modules, "jax", None)  # as if JAX were not installed
    assert not B.jax_available()
    with pytest.raises(B.BackendUnavailable, match=r"pip install 'gpnarx\[jax\]'"):
        sparse_model.simulate(u, method="linear", backend="jax")


def test_cli_predict_with_the_jax_backend(sparse_model, data, tmp_path, capsys):
    from gpnarx.cli.main import main
    from gpnarx.storage.bundle import save_bundle

    save_bundle(sparse_model, tmp_path / "reg", "duffing", fs=500.0, units={"u": "N", "y": "m"})
    rec = tmp_path / "r.npz"
    np.savez(rec, u=data["u2"], y=data["y2"], fs=500.0)
    outs = {}
    for be in ("numpy", "jax"):
        assert main(["predict", "--registry", str(tmp_path / "reg"), "--model", "duffing", str(rec), "--method",
                     "linear", "--backend", be, "--json"]) == 0
        outs[be] = json.loads(capsys.readouterr().out)
    assert outs["jax"]["backend"] == "jax" and outs["numpy"]["backend"] == "numpy"
    assert outs["jax"]["fit"] == pytest.approx(outs["numpy"]["fit"], abs=1e-6)
    out = tmp_path / "many"
    assert main(["predict-many", str(rec), "--registry", str(tmp_path / "reg"), "--model", "duffing", "--out",
                 str(out), "--method", "linear", "--backend", "jax", "--json"]) == 0
    capsys.readouterr()
    many = json.loads(next(p for p in out.glob("*.json") if p.name != "index.json").read_text())
    assert many["backend"] == "jax" and many["fit"] == pytest.approx(outs["jax"]["fit"], abs=1e-9)
    assert main(["predict", "--registry", str(tmp_path / "reg"), "--model", "duffing", str(rec), "--backend",
                 "cuda"]) != 0
    assert "invalid choice: 'cuda'" in capsys.readouterr().err
