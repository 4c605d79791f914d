"""The model with several inputs and outputs (issue 52): the regressors of eq. (3) over every channel, one GP
per output over the shared regressor, the free run feeding every output back together (linearised with the
joint covariance, Monte Carlo drawing all outputs at each step); with one output, GPNARX's numbers."""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.freerun.reference import simulate_mc_reference
from gpnarx.model.mimo import MIMOGPNARX
from gpnarx.model.record import Record
from gpnarx.model.regressors import mimo_columns, mimo_regressors, narx_regressors, stack_mimo_regressors


def _sdof(n=600, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    y = np.zeros(n)
    for i in range(2, n):
        y[i] = 1.5 * y[i - 1] - 0.7 * y[i - 2] + 0.3 * u[i] + 0.1 * u[i - 1] - 0.05 * y[i - 1] ** 3
    return u, y + 0.01 * rng.normal(size=n)


def _two_outputs(n=600, seed=0):
    """Two coupled outputs driven by one input: y1 a resonant filter of u, y2 a filter of y1 with a cubic term."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    y1, y2 = np.zeros(n), np.zeros(n)
    for i in range(2, n):
        y1[i] = 1.4 * y1[i - 1] - 0.6 * y1[i - 2] + 0.4 * u[i] - 0.05 * y1[i - 1] ** 3
        y2[i] = 0.7 * y2[i - 1] + 0.5 * y1[i - 1] - 0.1 * y2[i - 1] * y1[i - 1]
    return u, np.column_stack([y1, y2]) + 0.01 * rng.normal(size=(n, 2))


def test_mimo_regressors_eq3_for_every_channel():
    u, y = _sdof(50)
    X1, Y1 = narx_regressors(u, y, 3, 2)
    Xm, Ym = mimo_regressors(u, y, 3, 2)
    assert np.array_equal(X1, Xm) and np.array_equal(Y1, Ym[:, 0])  # one channel each: eq. (3) as it is
    rng = np.random.default_rng(1)
    U, Y = rng.normal(size=(30, 2)), rng.normal(size=(30, 3))
    X, T = mimo_regressors(U, Y, 2, 3)
    cols = mimo_columns(3, 2, 2, 3)
    assert X.shape == (28, 3 * 2 + 2 * 3) == (28, len(cols)) and T.shape == (28, 3)
    i0 = 2
    for c, (kind, ch, lag) in enumerate(cols):  # every column is the lag it says, of the channel it says
        src = Y if kind == "y" else U
        assert np.array_equal(X[:, c], src[i0 - lag: 30 - lag, ch]), (kind, ch, lag)
    assert np.array_equal(T, Y[i0:])
    Xs, Ts, idx = stack_mimo_regressors([(U, Y), (U[:10], Y[:10])], 2, 3)
    assert Xs.shape[0] == 28 + 8 and np.array_equal(idx, np.r_[np.zeros(28), np.ones(8)])
    with pytest.raises(ValueError, match="record 1: its channels differ"):
        stack_mimo_regressors([(U, Y), (U, Y[:, :2])], 2, 3)


@pytest.fixture(scope="module")
def pair():
    u, y = _sdof(500)
    kw = dict(ny=3, nu=2, max_train_points=250, n_restarts=0, seed=0)
    return u, y, GPNARX(**kw).fit([(u, y)]), MIMOGPNARX(**kw).fit([(u, y)])


def test_one_output_reduces_to_gpnarx(pair):
    u, y, single, mimo = pair
    g = mimo.outputs_[0]
    assert np.allclose(g.theta_, single.theta_, rtol=1e-10, atol=1e-12)
    assert g.noise_var_ == pytest.approx(single.noise_var_, rel=1e-10)
    m1, s1 = single.predict_one_step([(u, y)])
    mm, sm = mimo.predict_one_step([(u, y)])
    assert np.allclose(mm[:, 0], m1, rtol=1e-10, atol=1e-12) and np.allclose(sm[:, 0], s1, rtol=1e-10, atol=1e-12)
    ut = _sdof(300, seed=5)[0]
    # linearised: GPNARX's three-pass run, to round-off
    a = single.simulate(ut, method="linear")
    b = mimo.simulate(ut, method="linear")
    assert b.mean.shape == (300, 1)
    scale = np.max(np.abs(a.mean))
    assert np.max(np.abs(b.mean[:, 0] - a.mean)) < 1e-9 * scale
    assert np.allclose(b.std[:, 0], a.std, rtol=1e-7, atol=1e-12 * scale)
    assert np.allclose(b.latent_upper[:, 0], a.latent_upper, rtol=1e-7, atol=1e-9 * scale)
    # from measured outputs
    a0 = single.simulate(ut, method="linear", y0=y[:3])
    b0 = mimo.simulate(ut, method="linear", y0=y[:3, None])
    assert np.max(np.abs(b0.mean[:, 0] - a0.mean)) < 1e-9 * scale
    # Monte Carlo: eq. 8-9 at every path (GPNARX's reference loop), the same seed gives the same paths
    ref = simulate_mc_reference(single.posterior_, single.x_scaler_, single.y_scaler_, 3, 2, ut[:120], n_paths=64,
                                seed=3)
    mc = mimo.simulate(ut[:120], method="mc", n_paths=64, seed=3)
    for f in ("mean", "std", "lower", "upper", "latent_lower", "latent_upper"):
        assert np.allclose(getattr(mc, f)[:, 0], getattr(ref, f), rtol=1e-9, atol=1e-12 * scale), f
    one = MIMOGPNARX.channel_run(mc, 0)
    assert one.mean.shape == (120,) and np.array_equal(one.upper, mc.upper[:, 0])


@pytest.fixture(scope="module")
def two():
    u, y = _two_outputs(700)
    rec = Record(u, y, 100.0, channels={"u": [("F", "N")], "y": [("x1", "m"), ("x2", "m")]})
    m = MIMOGPNARX(ny=2, nu=2, max_train_points=300, n_restarts=0, n_jobs=2).fit([rec])
    return rec, m


def test_two_outputs_own_hyperparameters_and_parallel_fit(two):
    rec, m = two
    assert m.n_outputs_ == 2 and [c.name for c in m.output_channels_] == ["x1", "x2"]
    assert not np.allclose(m.outputs_[0].theta_, m.outputs_[1].theta_)  # each output its own ML-II
    serial = MIMOGPNARX(ny=2, nu=2, max_train_points=300, n_restarts=0, n_jobs=1).fit([rec])
    for a, b in zip(m.outputs_, serial.outputs_):  # threads give the numbers of the serial fit
        assert np.allclose(a.theta_, b.theta_, rtol=1e-8)
    # each output alone is that output's GPNARX-like fit on the shared regressor: one-step fit is good
    mean, std = m.predict_one_step([rec])
    resid = rec.y[2:] - mean
    assert np.all(np.sqrt(np.mean(resid ** 2, axis=0)) < 0.05 * np.std(rec.y, axis=0))


def test_two_outputs_free_run_joint_covariance_and_mc(two):
    rec, m = two
    u, y = _two_outputs(400, seed=9)
    lin = m.simulate(u, method="linear")
    mc = m.simulate(u, method="mc", n_paths=400, seed=0)
    assert lin.mean.shape == mc.mean.shape == (400, 2)
    for run in (lin, mc):
        err = y - run.mean
        fit = 100 * (1 - np.linalg.norm(err, axis=0) / np.linalg.norm(y - y.mean(axis=0), axis=0))
        assert np.all(fit > 80), fit
        inside = np.mean((y >= run.lower) & (y <= run.upper), axis=0)
        assert np.all(inside > 0.9), inside
    # the two propagations agree on the band where the model is nearly linear (within Monte Carlo error)
    assert np.median(np.abs(mc.std[50:] / lin.std[50:] - 1)) < 0.15
    # the joint propagation matters: x2 depends on x1's lags, so x2's linearised variance exceeds its own
    # GP's one-step variance once x1's uncertainty has propagated
    _, s1 = m.predict_one_step([(u, y)])
    assert np.median(lin.std[50:, 1]) > 2.0 * np.median(s1[48:, 1])
    with pytest.raises(ValueError, match=r"u must be \(n, 1\)"):
        m.simulate(np.ones((10, 2)))
    with pytest.raises(ValueError, match="y0 must hold"):
        m.simulate(u, y0=np.zeros((2, 1)))


def test_one_output_sparse_reduces_to_gpnarx():
    u, y = _sdof(500, seed=3)
    kw = dict(ny=2, nu=2, mode="sparse", n_inducing=40, max_train_points=200, n_restarts=0, seed=1)
    single, mimo = GPNARX(**kw).fit([(u, y)]), MIMOGPNARX(**kw).fit([(u, y)])
    assert mimo.outputs_[0].posterior_.kind == "sparse"
    assert np.allclose(mimo.outputs_[0].theta_, single.theta_, rtol=1e-10)
    ut = _sdof(200, seed=4)[0]
    a, b = single.simulate(ut, method="linear"), mimo.simulate(ut, method="linear")
    scale = np.max(np.abs(a.mean))
    assert np.max(np.abs(b.mean[:, 0] - a.mean)) < 1e-9 * scale
    assert np.allclose(b.std[:, 0], a.std, rtol=1e-7, atol=1e-12 * scale)


def test_two_inputs_two_outputs():
    """Each output driven by its own input and the other output: the model must use both inputs' lags."""

    def system(n, seed):
        r = np.random.default_rng(seed)
        U = r.normal(size=(n, 2))
        Y = np.zeros((n, 2))
        for i in range(1, n):
            Y[i, 0] = 0.6 * Y[i - 1, 0] + 0.5 * U[i, 0] + 0.2 * Y[i - 1, 1]
            Y[i, 1] = 0.5 * Y[i - 1, 1] + 0.4 * U[i - 1, 1] - 0.1 * Y[i - 1, 0] ** 2
        return U, Y + 0.01 * r.normal(size=(n, 2))

    U, Y = system(600, 1)
    m = MIMOGPNARX(ny=1, nu=2, max_train_points=300, n_restarts=0).fit([(U, Y)])
    assert m.n_inputs_ == 2 and m.n_features_ == 2 * 1 + 2 * 2
    Ut, Yt = system(300, 2)
    run = m.simulate(Ut, method="linear")
    fit = 100 * (1 - np.linalg.norm(Yt - run.mean, axis=0) / np.linalg.norm(Yt - Yt.mean(axis=0), axis=0))
    assert np.all(fit > 90), fit
    # a model that sees only the first input cannot follow the second output, driven by the second input
    one = MIMOGPNARX(ny=1, nu=2, max_train_points=300, n_restarts=0).fit([(U[:, 0], Y)])
    r1 = one.simulate(Ut[:, 0], method="linear")
    fit1 = 100 * (1 - np.linalg.norm(Yt[:, 1] - r1.mean[:, 1]) / np.linalg.norm(Yt[:, 1] - Yt[:, 1].mean()))
    assert fit1 < fit[1] - 30, (fit1, fit)
    with pytest.raises(ValueError, match=r"u must be \(n, 2\)"):
        m.simulate(Ut[:, 0])


class _LinearGaussian:
    """A posterior-shaped linear Gaussian model: mean a . x, latent variance v, noise variance s2 (the linearised
    run is then exact, and its covariance can be checked against the state-space recursion)."""

    def __init__(self, a, v, s2):
        self.a, self.v, self.noise_var = np.asarray(a, float), float(v), float(s2)
        self.mean_weights, self.mean_shift = self.a, 0.0

    def cross(self, X):
        return np.asarray(X)

    def mean_var_grad(self, X):
        return X @ self.a, np.full(X.shape[0], self.v), np.tile(self.a, (X.shape[0], 1))

    def predict(self, X, return_var=True, float32=False):
        return X @ self.a, np.full(X.shape[0], self.v)


def test_joint_covariance_is_the_state_space_recursion_for_a_linear_model():
    from gpnarx.model.freerun import RunSpec
    from gpnarx.model.freerun.mimo import MIMOPredictor, run_mimo_linear, run_mimo_mc

    # two coupled outputs, ny = 2, one input: regressor [y0_{i-1}, y0_{i-2}, y1_{i-1}, y1_{i-2}, u_i]
    a0 = np.array([1.2, -0.5, 0.3, 0.0, 1.0])
    a1 = np.array([0.4, 0.1, 0.5, -0.2, 0.0])
    posts = (_LinearGaussian(a0, 0.01, 0.02), _LinearGaussian(a1, 0.03, 0.01))
    pred = MIMOPredictor(posts, np.zeros(5), np.ones(5), np.zeros(2), np.ones(2), 2, 1, 1)
    u = np.sin(np.arange(150) / 5)
    lin = run_mimo_linear(pred, u, RunSpec(method="linear"))
    # the state-space recursion, written apart: r = [y0_{i-1}, y0_{i-2}, y1_{i-1}, y1_{i-2}], r' = F r + G u + e
    F = np.array([a0[:4], [1, 0, 0, 0], a1[:4], [0, 0, 1, 0]], float)
    Q = np.diag([0.03, 0, 0.04, 0])
    P, std = np.zeros((4, 4)), np.zeros((150, 2))
    for i in range(150):
        P = F @ P @ F.T + Q
        std[i] = np.sqrt(P[[0, 2], [0, 2]])
    assert np.allclose(lin.std, std, rtol=1e-12, atol=0)
    mc = run_mimo_mc(pred, u, RunSpec(method="mc", n_paths=4000, seed=0))
    assert np.max(np.abs(mc.std[10:] / std[10:] - 1)) < 0.1  # Monte Carlo draws every output from the same law


def test_joint_covariance_stays_symmetric_on_a_stiff_pair():
    """Two sensors of the chain (noise-free, short training): J S J^T's round-off is not symmetric, and an
    asymmetric S grew by about 9x a step until the band hit its cap and the variance went negative; the
    linearised band must follow Monte Carlo's."""
    from gpnarx.training.excitations import swept_sine
    from gpnarx.training.simulators.chain import Chain

    chain = Chain()
    recs = []
    for amp in (3.0, 5.0):
        u = swept_sine(chain.fs, amp, 2.0, 50.0, duration=3.0)
        recs.append((u, chain.simulate(u)["y"][:, [0, 2]]))
    m = MIMOGPNARX(ny=4, nu=3, max_train_points=200, n_restarts=0).fit([recs[0]])
    lin = m.simulate(recs[1][0], method="linear")
    mc = m.simulate(recs[1][0], method="mc", n_paths=200, seed=0)
    assert np.all(lin.std[5:] > 0) and np.all(np.isfinite(lin.std))
    ratio = np.median(lin.std[5:], axis=0) / np.median(mc.std[5:], axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


def test_one_output_noise_and_band_calibration_reduce_to_gpnarx():
    u, y = _sdof(500, seed=11)
    uh, yh = _sdof(300, seed=12)
    uc, yc = _sdof(300, seed=13)
    yh = yh + 0.05 * np.random.default_rng(1).normal(size=300)  # held-out records noisier than training
    kw = dict(ny=3, nu=2, max_train_points=250, n_restarts=0, seed=0)
    single = GPNARX(**kw).fit([(u, y)], heldout=[(uh, yh)])
    mimo = MIMOGPNARX(**kw).fit([(u, y)], heldout=[(uh, yh)])
    assert single.noise_var_ > single.noise_var_ml2_  # the calibration raised it
    assert mimo.outputs_[0].noise_var_ == pytest.approx(single.noise_var_, rel=1e-10)
    # a drive twice the training level: the model's form error, which the discrepancy term must cover
    u2 = 2.0 * uc
    y2 = np.zeros(300)
    for i in range(2, 300):
        y2[i] = 1.5 * y2[i - 1] - 0.7 * y2[i - 2] + 0.3 * u2[i] + 0.1 * u2[i - 1] - 0.05 * y2[i - 1] ** 3
    recs = [("c", uc, yc, "rest"), ("h", uh, yh, "measured"), ("2x", u2, y2, "rest")]
    from gpnarx.model.discrepancy import GP_SCALE_GRID

    d1 = single.calibrate_band(recs, window=25, kind="trailing", hold=10, gp_scales=GP_SCALE_GRID)
    d2 = mimo.calibrate_band(recs, window=25, kind="trailing", hold=10, gp_scales=GP_SCALE_GRID)[0]
    assert d1["scale"] > 0 and d2["channel"] == "y"
    assert (d2["scale"], d2["gp_scale"]) == (d1["scale"], d1["gp_scale"])
    ut = _sdof(200, seed=14)[0]
    a, b = single.simulate(ut, method="linear"), mimo.simulate(ut, method="linear")
    scale = np.max(np.abs(a.mean))
    for f in ("std", "lower", "upper", "latent_upper"):
        assert np.allclose(getattr(b, f)[:, 0], getattr(a, f), rtol=1e-7, atol=1e-9 * scale), f
    # the terms travel with the model's description
    back = MIMOGPNARX.from_fitted(mimo.fitted_description(), mimo.fitted_arrays())
    assert back.band_discrepancy_[0]["scale"] == d2["scale"]
    assert np.array_equal(back.simulate(ut, method="linear").upper, b.upper)
