"""The residual tests of model.residual_tests against known truths: the FFT correlations against their sums,
Ljung-Box against statsmodels (else its closed form), the limits' false-alarm rate on white noise, an exact
ARX model's one-step residuals pass and a model with too few lags fails, an input-correlated residual is
caught by the cross-correlation only."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from gpnarx.model import residual_tests as rt


def _direct_acf(e, lags):
    d = e - e.mean()
    c0 = d @ d
    return np.array([d[k:] @ d[:-k] for k in range(1, lags + 1)]) / c0


def _direct_ccf(u, e, lags):
    du, de = u - u.mean(), e - e.mean()
    n = e.size
    out = []
    for k in range(-lags, lags + 1):  # (1/N) sum_t u(t) e(t+k)
        out.append(du[:n - k] @ de[k:] if k >= 0 else du[-k:] @ de[:n + k])
    return np.array(out) / math.sqrt((du @ du) * (de @ de))


def _arx(n, seed, noise=0.05):
    """y(t) = 1.5 y(t-1) - 0.7 y(t-2) + 0.5 u(t) + 0.3 u(t-1) + w(t), u and w white: ny = nu = 2 is exact."""
    r = np.random.default_rng(seed)
    u, w = r.normal(size=n), noise * r.normal(size=n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + 0.5 * u[t] + 0.3 * u[t - 1] + w[t]
    return u, y


@pytest.mark.parametrize("n, lags", [(1000, 25), (257, 128), (4099, 7)])
def test_fft_correlations_equal_their_sums(n, lags):
    r = np.random.default_rng(n)
    u = r.normal(size=n)
    e = np.convolve(r.normal(size=n), [1.0, 0.6, -0.2])[:n] + 0.4 * np.roll(u, 3)
    np.testing.assert_allclose(rt.autocorrelation(e, lags), _direct_acf(e, lags), rtol=0, atol=1e-12)
    x = rt.cross_correlation(u, e, lags)
    assert x.shape == (2 * lags + 1,)
    np.testing.assert_allclose(x, _direct_ccf(u, e, lags), rtol=0, atol=1e-12)


def test_ljung_box_against_statsmodels_or_its_closed_form():
    """Q = N (N + 2) sum r_k^2 / (N - k) and its chi-square tail: against statsmodels' acorr_ljungbox where
    installed, else the sum written out and, for an even df, the tail's closed form
    exp(-q/2) sum_{i < df/2} (q/2)^i / i! (no scipy)."""
    r = np.random.default_rng(3)
    e = np.convolve(r.normal(size=800), [1.0, 0.15])[:800]  # mildly coloured: a p-value inside (0, 1)
    lags = 24
    got = rt.residual_tests(e, lags=lags)["autocorrelation"]["ljung_box"]
    try:
        from statsmodels.stats.diagnostic import acorr_ljungbox
    except ImportError:
        acf = _direct_acf(e, lags)
        n = e.size
        q = n * (n + 2) * sum(acf[k - 1] ** 2 / (n - k) for k in range(1, lags + 1))
        p = math.exp(-q / 2) * sum((q / 2) ** i / math.factorial(i) for i in range(lags // 2))
    else:
        table = acorr_ljungbox(e, lags=[lags])
        q, p = float(table["lb_stat"].iloc[0]), float(table["lb_pvalue"].iloc[0])
    assert got["df"] == lags
    assert got["q"] == pytest.approx(q, rel=1e-10)
    assert got["p_value"] == pytest.approx(p, rel=1e-8)
    assert 1e-6 < got["p_value"] < 0.5


def test_limits_hold_their_confidence_on_white_noise():
    """On 300 white records the share of lags outside the 99 % limits averages about 1 %, and each verdict
    (Ljung-Box, cross portmanteau) rejects about 1 % of them: the limits are what they say."""
    r = np.random.default_rng(11)
    shares, xshares, rejected, xrejected = [], [], 0, 0
    for _ in range(300):
        e, u = r.normal(size=2000), r.normal(size=2000)
        out = rt.residual_tests(e, u, lags=25)
        assert out["limit"] == pytest.approx(2.5758293035489 / math.sqrt(2000), rel=1e-12)
        shares.append(out["autocorrelation"]["outside_share"])
        xshares.append(out["cross_correlation"]["outside_share"])
        rejected += not out["autocorrelation"]["white"]
        xrejected += not out["cross_correlation"]["independent"]
    assert 0.005 < np.mean(shares) < 0.016 and 0.005 < np.mean(xshares) < 0.016
    # binomial(300, 0.01): mean 3, P(X > 10) < 1e-3
    assert rejected <= 10 and xrejected <= 10


def test_an_input_correlated_residual_fails_the_cross_test_only():
    """e = w + 0.3 u(t - 3) with u and w white: e is still white (Ljung-Box passes), but its cross-correlation
    with u stands out at lag +3, the input 3 samples before the residual."""
    r = np.random.default_rng(5)
    n = 4000
    u, w = r.normal(size=n), r.normal(size=n)
    e = w.copy()
    e[3:] += 0.3 * u[:-3]
    out = rt.residual_tests(e, u)
    assert out["autocorrelation"]["white"] is True
    x = out["cross_correlation"]
    assert x["independent"] is False and out["passed"] is False
    lag_of_peak = x["lag"][int(np.argmax(np.abs(x["r"])))]
    assert lag_of_peak == 3 and abs(x["r"][x["lag"].index(3)]) > 5 * out["limit"]
    assert x["portmanteau"]["df"] == 51 and x["portmanteau"]["p_value"] < 1e-10


@pytest.fixture(scope="module")
def arx_models():
    from gpnarx.model.estimator import GPNARX

    u, y = _arx(1500, 1)
    exact = GPNARX(ny=2, nu=2, max_train_points=300, n_restarts=0).fit([(u, y)])
    short = GPNARX(ny=1, nu=1, max_train_points=300, n_restarts=0).fit([(u, y)])
    return exact, short


def test_an_exact_arx_models_residuals_pass(arx_models):
    """The GP-NARX with the ARX record's own lags (ny = nu = 2) leaves white residuals uncorrelated with the
    input on a fresh record: both verdicts pass and the share of lags outside stays near 1 % (at most 2 of
    25; 2 of 51)."""
    exact, _ = arx_models
    u, y = _arx(2000, 2)
    out = rt.one_step_check(exact, u, y, with_std=True)
    t = out["residual_tests"]
    assert out["n"] == 2000 - 2 and t["n"] == out["n"]
    assert t["passed"] is True
    assert t["autocorrelation"]["outside_share"] <= 2 / 25
    assert t["cross_correlation"]["outside_share"] <= 2 / 51
    assert t["autocorrelation"]["ljung_box"]["p_value"] > 0.01
    assert out["fit"] > 95 and 97 < out["coverage"] <= 100 and 0.9 < out["z_rms"] < 1.1


def test_a_model_with_too_few_lags_fails(arx_models):
    """ny = nu = 1 cannot hold the ARX's second-order dynamics: its one-step residuals are coloured and
    correlate with the input (most lags outside, both p-values ~ 0), although its one-step band still
    covers them: the tests see what coverage does not."""
    _, short = arx_models
    u, y = _arx(2000, 2)
    out = rt.one_step_check(short, u, y, with_std=True)
    t = out["residual_tests"]
    assert t["passed"] is False
    assert t["autocorrelation"]["white"] is False and t["cross_correlation"]["independent"] is False
    assert t["autocorrelation"]["outside_share"] > 0.3 and t["autocorrelation"]["ljung_box"]["p_value"] < 1e-10
    assert t["cross_correlation"]["outside_share"] > 0.1
    assert out["coverage"] > 97


def test_one_step_prediction_in_blocks_equals_one_call(arx_models):
    exact, _ = arx_models
    u, y = _arx(700, 4)
    mean, std = exact.predict_one_step([(u, y)])
    i0, m, s = rt.one_step_prediction(exact, u, y, with_std=True, block=97)
    assert i0 == 2
    # the same rows, multiplied in other blocks: equal to round-off of the products' sums
    tol = dict(rtol=0, atol=1e-11 * np.max(np.abs(mean)))
    np.testing.assert_allclose(m, mean, **tol)
    np.testing.assert_allclose(s, std, rtol=1e-9)
    i0, m, s = rt.one_step_prediction(exact, u, y, block=10_000)
    assert s is None
    np.testing.assert_allclose(m, mean, **tol)


def test_what_it_refuses():
    e = np.random.default_rng(0).normal(size=60)
    with pytest.raises(ValueError, match="more than 50 residuals"):
        rt.residual_tests(e[:50], lags=25)
    bad = e.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="gap-free"):
        rt.residual_tests(bad, lags=5)
    with pytest.raises(ValueError, match="positive integer"):
        rt.residual_tests(e, lags=0)
    with pytest.raises(ValueError, match="same length"):
        rt.residual_tests(e, e[:-1], lags=5)
    flat = rt.residual_tests(e, np.ones(60), lags=5)  # a constant input: no cross-correlation to normalise
    assert flat["cross_correlation"]["independent"] is None and flat["passed"] is None
    assert flat["autocorrelation"]["white"] in (True, False)


def test_importing_it_loads_no_scipy_stats():
    code = ("import sys, gpnarx.model.residual_tests\n"
            "print([m for m in ('scipy.stats', 'scipy.special', 'scipy.signal') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
