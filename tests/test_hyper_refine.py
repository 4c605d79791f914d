"""training.hyper_refine: the lengthscales refined by free-run fit on the 'lags' records."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.kernels import make_kernel
from gpnarx.model.metrics import fit_percent
from gpnarx.model.record import Record
from gpnarx.training.hyper_refine import STEP, lengthscale_indices, refine_lengthscales


def _duffing(u, fs=400.0):
    """A softly nonlinear oscillator (20 Hz, 3 % damping, cubic stiffness), semi-implicit Euler; y [m]."""
    wn, z, k3 = 2 * np.pi * 20.0, 0.03, 4e6
    dt = 1.0 / fs
    x = v = 0.0
    y = np.empty(u.size)
    for i, f in enumerate(u):
        y[i] = x
        for _ in range(4):
            a = f - 2 * z * wn * v - wn**2 * x - k3 * x**3
            v += a * dt / 4
            x += v * dt / 4
    return y


@pytest.fixture(scope="module")
def small():
    rng = np.random.default_rng(3)
    recs = []
    for k, amp in enumerate((30.0, 60.0, 45.0)):
        u = amp * rng.normal(size=1200)
        y = _duffing(u)
        y = y + 0.01 * np.std(y) * rng.normal(size=y.size)
        recs.append(Record(u=u, y=y, fs=400.0, name=f"r{k}", meta={"initial": "rest"}))
    model = GPNARX(ny=3, nu=3, max_train_points=300, n_restarts=0).fit(recs[:1])
    return model, recs[1:]


def test_lengthscale_indices():
    assert lengthscale_indices(make_kernel("matern32+cubic")) == [1]
    assert lengthscale_indices(make_kernel("rbf")) == [1]
    k = make_kernel("matern32+cubic")
    k.set_theta(np.arange(k.n_params, dtype=float))
    assert [k.get_theta()[i] for i in lengthscale_indices(k)] == [np.log(k.parts[0].params["lengthscale"])]
    assert lengthscale_indices(make_kernel("cubic")) == []


def test_rule_and_posterior(small):
    base, lags = small
    model = copy.deepcopy(base)
    ls0 = model.kernel_.parts[0].params["lengthscale"]
    out = refine_lengthscales(model, lags, tolerance=1.0)
    cands = out["candidates"]
    assert cands[0]["factor"] == 1.0 and cands[0]["admissible"]
    fits0 = cands[0]["fits"]
    for c in cands:  # the admissible flag is the documented tolerance test
        assert c["admissible"] == all(c["fits"][n] >= fits0[n] - 1.0 for n in fits0)
        assert c["worst"] == pytest.approx(min(c["fits"].values()))
        k = round(np.log(c["factor"]) / STEP)
        assert c["factor"] == pytest.approx(np.exp(k * STEP), rel=1e-12)
    kept = [c for c in cands if c["admissible"]]
    assert out["worst_fit"] == pytest.approx(max(c["worst"] for c in kept))
    assert out["worst_fit"] >= out["worst_fit_ml2"]
    # the model holds the kept factor: its lengthscale, and a posterior equal to a fit at those hyperparameters
    assert model.kernel_.parts[0].params["lengthscale"] == pytest.approx(ls0 * out["factor"], rel=1e-12)
    # and its free run scores what the rule recorded for it
    for rec in lags:
        f = fit_percent(rec.y, model.simulate(rec.u, method="linear").mean)
        assert f == pytest.approx(next(c for c in cands if c["factor"] == out["factor"])["fits"][rec.name], abs=1e-9)
    assert model.hyper_refinement_ is out


def test_tolerance_zero_never_loses(small):
    base, lags = small
    model = copy.deepcopy(base)
    out = refine_lengthscales(model, lags, tolerance=0.0)
    f0 = out["candidates"][0]["fits"]
    kept = next(c for c in out["candidates"] if c["factor"] == out["factor"])
    assert all(kept["fits"][n] >= f0[n] for n in f0)


def test_refit_at_kept_hyperparameters_matches(small):
    """The refined posterior equals ``fit(theta=...)`` at the kept hyperparameters on the same rows."""
    rng = np.random.default_rng(3)
    u = 30.0 * rng.normal(size=1200)
    y = _duffing(u)
    y = y + 0.01 * np.std(y) * rng.normal(size=y.size)
    train = [Record(u=u, y=y, fs=400.0, name="r0", meta={"initial": "rest"})]
    _, lags = small
    model = GPNARX(ny=3, nu=3, max_train_points=300, n_restarts=0).fit(train)
    refine_lengthscales(model, lags, tolerance=5.0)
    ref = GPNARX(ny=3, nu=3, max_train_points=300, n_restarts=0).fit(train, theta=model.theta_)
    X = model.posterior_.X_train[:50]
    m1, v1 = model.posterior_.predict(X)
    m2, v2 = ref.posterior_.predict(X)
    np.testing.assert_allclose(m1, m2, atol=1e-8)
    np.testing.assert_allclose(v1, v2, atol=1e-8)


def test_errors(small):
    base, lags = small
    with pytest.raises(ValueError, match="role 'lags'"):
        refine_lengthscales(copy.deepcopy(base), [])
    with pytest.raises(ValueError, match="tolerance"):
        refine_lengthscales(copy.deepcopy(base), lags, tolerance=-1.0)


def test_markdown_renders_every_candidate(small):
    from gpnarx.training.hyper_refine import markdown

    base, lags = small
    model = copy.deepcopy(base)
    out = refine_lengthscales(model, lags, tolerance=1.0)
    page = markdown(out)
    rows = [line for line in page.splitlines() if line.startswith("| ") and not line.startswith("| lengthscale")]
    assert len(rows) == len(out["candidates"])
    assert f"| **{out['factor']:.2f}** |" in page
    assert all(f"{r.name} fit %" in page for r in lags)
    assert "ML-II" in markdown({"skipped": "the posterior is sparse"})
