"""k-step-ahead prediction (``model.freerun.horizon``, ``GPNARX.simulate(horizon=k)``) and records with gaps
(``model.gaps``: training and prediction)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import sdof_simulate

from gpnarx.model.estimator import GPNARX
from gpnarx.model.freerun import FreeRunState, RunSpec
from gpnarx.model.freerun.horizon import run_horizon
from gpnarx.model.freerun.linear import run_linear
from gpnarx.model.gaps import GapError, check_gaps, find_gaps, pieces
from gpnarx.model.metrics import coverage, fit_percent, summary
from gpnarx.model.normal import band_z
from gpnarx.model.regressors import narx_regressors, stack_regressors

NY, NU = 4, 6  # nu - 1 > ny: the input lags reach further back than the output lags


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(1)
    u = rng.normal(size=1200)
    y = sdof_simulate(u)
    y = y + 0.03 * np.std(y) * rng.normal(size=y.size)
    return u, y


@pytest.fixture(scope="module")
def model(data):
    u, y = data
    return GPNARX(ny=NY, nu=NU, max_train_points=300, n_restarts=0).fit([(u[:800], y[:800])])


@pytest.fixture(scope="module")
def record(data):
    u, y = data
    return u[800:], y[800:]


def _close(a, b, rel=1e-10):
    scale = max(1e-300, float(np.max(np.abs(b))))
    assert np.max(np.abs(np.asarray(a) - np.asarray(b))) <= rel * scale, np.max(np.abs(np.asarray(a) - b)) / scale


# ------------------------------------------------------------------------------------------ k-step
@pytest.mark.parametrize("method", ["linear", "mc"])
def test_k1_is_the_one_step_prediction(model, record, method):
    """k = 1: eqs. 8-9 at the measured regressors, mean, std and band, as predict_one_step (round-off)."""
    u, y = record
    mean, std = model.predict_one_step([(u, y)])
    run = model.simulate(u, y=y, horizon=1, method=method, n_paths=64)
    i0 = max(NY, NU - 1)  # predict_one_step's first row
    _close(run.mean[i0:], mean)
    _close(run.std[i0:], std)
    z = band_z(0.99)
    _close(run.lower[i0:], mean - z * std)
    _close(run.upper[i0:], mean + z * std)
    assert np.array_equal(run.mean[:NY], y[:NY]) and not np.any(run.std[:NY])  # the measured start
    assert model.include_noise and np.all(run.latent_upper[i0:] < run.upper[i0:])  # sigma_y^2 in the band only


def test_k_step_band_leaves_out_the_discrepancy_term_and_follows_include_noise(model, record):
    """The band of a k-step answer is eqs. 8-9's: a calibrated discrepancy term (which widens the free run's band)
    is not added, and without include_noise its sigma_y^2 is left out as predict_one_step leaves it out."""
    import copy

    u, y = record
    m = copy.deepcopy(model)
    m.band_discrepancy_ = {"scale": 0.2, "window": 32}
    i0 = max(NY, NU - 1)
    mean, std = model.predict_one_step([(u, y)])
    run = m.simulate(u, y=y, horizon=1, method="linear")
    _close(run.std[i0:], std)
    free, free_disc = model.simulate(u, y0=y[:NY], method="linear"), m.simulate(u, y0=y[:NY], method="linear")
    assert np.all(free_disc.std[NY:] > free.std[NY:])  # the term widens the free run ...
    k_n = m.simulate(u, y=y, horizon=u.size, method="linear")
    assert np.array_equal(k_n.std, free.std)  # ... and not the k-step answer, even at k = n
    m.include_noise = False
    quiet = m.simulate(u, y=y, horizon=1, method="linear")
    _close(quiet.std[i0:], m.predict_one_step([(u, y)])[1])
    assert np.all(quiet.std[i0:] < std)


@pytest.mark.parametrize("method", ["linear", "mc"])
def test_k_n_is_the_free_run_from_the_measured_start(model, record, method):
    u, y = record
    free = model.simulate(u, y0=y[:NY], method=method, n_paths=128, seed=3)
    run = model.simulate(u, y=y, horizon=u.size, method=method, n_paths=128, seed=3)
    for name in ("mean", "std", "lower", "upper"):
        assert np.array_equal(getattr(run, name), getattr(free, name)), name
    # any horizon at least the predicted length is one segment
    again = model.simulate(u, y=y, horizon=u.size - NY, method=method, n_paths=128, seed=3)
    assert np.array_equal(again.mean, free.mean)


def test_linear_batch_of_one_segment_is_the_free_run(model, record):
    """The batched linearised k-step, forced on one segment, gives the free run's numbers to round-off."""
    u, y = record
    free = model.simulate(u, y0=y[:NY], method="linear")
    spec = RunSpec(method="linear", include_noise=model.include_noise)
    run = run_horizon(model.predictor(), u, y, spec, u.size, batch=True)
    for name in ("mean", "std", "lower", "upper", "latent_lower", "latent_upper"):
        _close(getattr(run, name), getattr(free, name), 1e-9)


@pytest.mark.parametrize("k", [8, 64])
def test_linear_batch_is_each_segment_restarted(model, record, k):
    """Every segment of the batch equals a free run continued from a state whose lags are the measured
    outputs, with no covariance, and the record's own input lags."""
    u, y = record
    p = model.predictor()
    run = model.simulate(u, y=y, horizon=k, method="linear")
    spec = RunSpec(method="linear", include_noise=model.include_noise)
    n = u.size
    for s in (NY, NY + k, NY + 5 * k, n - ((n - NY) % k or k)):
        e = min(n, s + k)
        u_tail = np.concatenate([np.zeros(NU), u])[s + 1: s + NU]  # u_{s-nu+1} .. u_{s-1}, zeros before the record
        state = FreeRunState("linear", s, u_tail, mean_tail=y[s - NY: s].copy(), cov=np.zeros((NY, NY)))
        ref = run_linear(p, u[s:e], RunSpec(**{**spec.__dict__, "state": state}))
        _close(run.mean[s:e], ref.mean, 1e-9)
        _close(run.std[s:e], ref.std, 1e-9)


def test_linear_batch_in_groups_gives_the_same_numbers(model, record, monkeypatch):
    """Segments run in groups (bounded memory: ``_GROUP_ROWS``, ``_GROUP_FLOATS``): the numbers of one batch, and
    the progress callback reaches the record's length."""
    import gpnarx.model.freerun.horizon as hz

    u, y = record
    whole = model.simulate(u, y=y, horizon=8, method="linear")
    seen = []
    monkeypatch.setattr(hz, "_GROUP_ROWS", 7)
    grouped = model.simulate(u, y=y, horizon=8, method="linear", progress=lambda done, total: seen.append(done))
    _close(grouped.mean, whole.mean, 1e-9)  # BLAS rounds a row by the block it is in
    _close(grouped.std, whole.std, 1e-9)  # eq. 9 is a difference of near numbers: its round-off is larger
    assert len(seen) == -(-(u.size - NY) // (8 * 7)) and seen[-1] == u.size


@pytest.mark.parametrize("method", ["linear", "mc"])
def test_band_grows_within_a_segment_and_resets(model, record, method):
    u, y = record
    k = 16
    run = model.simulate(u, y=y, horizon=k, method=method, n_paths=256)
    starts = np.arange(NY, u.size - k, k)
    first, last = run.std[starts], run.std[starts + k - 1]
    assert np.median(last / first) > 1.5  # k steps from the measured outputs: wider than one
    one = model.simulate(u, y=y, horizon=1, method="linear")
    if method == "linear":
        _close(first, one.std[starts], 1e-9)  # a restart's first step is the one-step band
    else:
        assert np.allclose(first, one.std[starts], rtol=0.25)  # the paths' spread, 256 paths


def test_fit_falls_as_the_horizon_grows(model, record):
    u, y = record
    fits = [fit_percent(y, model.simulate(u, y=y, horizon=k, method="linear").mean) for k in (1, 8, 64)]
    free = fit_percent(y, model.simulate(u, y0=y[:NY], method="linear").mean)
    assert fits[0] > fits[1] > fits[2] > free, (fits, free)
    mc = model.simulate(u, y=y, horizon=8, method="mc", n_paths=256, seed=1)
    assert abs(fit_percent(y, mc.mean) - fits[1]) < 2.0
    assert np.array_equal(mc.mean, model.simulate(u, y=y, horizon=8, method="mc", n_paths=256, seed=1).mean)
    assert coverage(y, mc.lower, mc.upper) > 90


def test_horizon_refusals(model, record):
    u, y = record
    with pytest.raises(ValueError, match="^y: .*measured output"):
        model.simulate(u, horizon=8)
    for bad in (0, -1, 2.5, "8", True):
        with pytest.raises(ValueError, match="^horizon must be an integer >= 1"):
            model.simulate(u, y=y, horizon=bad)
    with pytest.raises(ValueError, match="^y has 10 samples"):
        model.simulate(u, y=y[:10], horizon=8)
    with pytest.raises(ValueError, match="^horizon: .*numpy backend"):
        model.simulate(u, y=y, horizon=8, backend="jax")
    run = model.simulate(u, y0=y[:NY], method="linear", open_end=True)
    with pytest.raises(ValueError, match="^state: a k-step prediction"):
        model.simulate(u, y=y, horizon=8, method="linear", state=run.state)
    with pytest.raises(ValueError, match="longer than ny"):
        model.simulate(u[:NY], y=y[:NY], horizon=2)
    with pytest.raises(ValueError, match="^horizon: .*y0 does not apply"):
        model.simulate(u, y=y, horizon=8, y0=y[:NY])


# ------------------------------------------------------------------------------------------ gaps: training
def test_a_gap_never_enters_a_lag_window():
    rng = np.random.default_rng(4)
    for trial in range(30):
        n = int(rng.integers(40, 200))
        u, y = rng.normal(size=n), rng.normal(size=n)
        for _ in range(int(rng.integers(1, 4))):
            a = int(rng.integers(0, n - 1))
            (u if rng.random() < 0.5 else y)[a: a + int(rng.integers(1, 12))] = np.nan
        ny, nu = int(rng.integers(1, 6)), int(rng.integers(1, 8))
        parts = [(u[a:b], y[a:b]) for a, b in pieces(n, find_gaps(u, y)) if b - a > max(ny, nu - 1)]
        if not parts:
            with pytest.raises(ValueError, match="no complete lag window outside its gaps"):
                narx_regressors(u, y, ny, nu)
            continue
        X, Y = narx_regressors(u, y, ny, nu)
        assert np.all(np.isfinite(X)) and np.all(np.isfinite(Y))
        Xp, Yp, _ = stack_regressors(parts, ny, nu)  # the pieces as records of their own
        assert np.array_equal(X, Xp) and np.array_equal(Y, Yp), trial


def test_a_record_with_a_gap_trains_as_its_two_pieces(data):
    u, y = (a[:800].copy() for a in data)
    ug = u.copy()
    ug[300:340] = np.nan
    theta = GPNARX(ny=NY, nu=NU, max_train_points=300, n_restarts=0).fit([(u, y)]).theta_
    kw = dict(ny=NY, nu=NU, max_train_points=10_000, n_restarts=0)
    one = GPNARX(**kw).fit([(ug, y)], theta=theta)
    two = GPNARX(**kw).fit([(u[:300], y[:300]), (u[340:], y[340:])], theta=theta)
    assert np.array_equal(one.posterior_.alpha, two.posterior_.alpha)
    assert one.envelope_["u_peak"] == two.envelope_["u_peak"]
    # an infinite value is still refused
    with pytest.raises(ValueError, match="non-finite"):
        GPNARX(**kw).fit([(np.r_[u[:-1], np.inf], y)], theta=theta)


# ------------------------------------------------------------------------------------------ gaps: prediction
@pytest.mark.parametrize("method", ["linear", "mc"])
def test_prediction_holds_nan_through_a_gap_and_restarts_after_it(model, record, method):
    u, y = record
    a, b = 150, 190
    ug = u.copy()
    ug[a:b] = np.nan
    kw = dict(method=method, n_paths=64, seed=2)
    run = model.simulate(ug, y=y, **kw)
    assert np.all(np.isnan(run.mean[a:b])) and np.all(np.isnan(run.upper[a:b]))
    before = model.simulate(u[:a], **kw)  # the first piece as asked: from rest
    after = model.simulate(u[b:], y0=y[b:b + NY], **{**kw, "seed": 3})  # from the measured outputs, seed + 1
    assert np.array_equal(run.mean[:a], before.mean) and np.array_equal(run.lower[:a], before.lower)
    assert np.array_equal(run.mean[b:], after.mean) and np.array_equal(run.upper[b:], after.upper)
    rest = model.simulate(ug, **kw)  # without y: from rest after the gap
    assert np.array_equal(rest.mean[b:], model.simulate(u[b:], **{**kw, "seed": 3}).mean)
    # a k-step prediction of a record with a gap: each piece its own k-step prediction
    ks = model.simulate(ug, y=y, horizon=8, **kw)
    assert np.all(np.isnan(ks.mean[a:b]))
    assert np.array_equal(ks.mean[b:], model.simulate(u[b:], y=y[b:], horizon=8, **{**kw, "seed": 3}).mean)
    # a gap in y alone is a gap too
    yg = y.copy()
    yg[a:b] = np.nan
    assert np.array_equal(np.isnan(model.simulate(u, y=yg, **kw).mean), np.isnan(run.mean))


def test_metrics_skip_the_gaps(model, record):
    u, y = record
    ug = u.copy()
    ug[100:160] = np.nan
    run = model.simulate(ug, y=y, method="linear")
    keep = ~np.isnan(run.mean)
    s = summary(y, run.mean, run.lower, run.upper)
    assert np.isfinite(s["fit"]) and s["fit"] == fit_percent(y[keep], run.mean[keep])
    assert s["coverage"] == coverage(y[keep], run.lower[keep], run.upper[keep])


def test_gap_limits_name_the_field():
    fs = 100.0
    u, y = np.zeros(1000), np.zeros(1000)
    assert check_gaps(u, y, fs) == []
    u[10:210] = np.nan  # 2.0 s: at the limit
    assert check_gaps(u, y, fs) == [(10, 210)]
    y[400:601] = np.nan  # 2.01 s
    with pytest.raises(GapError, match="^y has a gap of 201 samples") as e:
        check_gaps(u, y, fs)
    assert e.value.field == "y" and e.value.limit == 2.0
    u, y = np.zeros(1000), np.zeros(1000)
    for a in range(0, 1000, 100):
        u[a: a + 55] = np.nan  # 55 % missing, no gap longer than the limit
    with pytest.raises(GapError, match="550 of 1000 samples are missing") as e:
        check_gaps(u, y, fs)
    assert e.value.field == "u" and e.value.limit == 0.5
