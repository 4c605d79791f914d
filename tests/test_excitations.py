"""Excitation signals: frequencies, spectra, levels, seeds, argument errors."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gpnarx.training import excitations as ex


def _upward_crossings(x, fs):
    """Times [s] of upward zero crossings, linearly interpolated."""
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    frac = -x[i] / (x[i + 1] - x[i])
    return (i + frac) / fs


@pytest.mark.parametrize("f0,f1,rate", [(5.0, 150.0, 53.0), (0.0, 40.0, 5.0)])
def test_swept_sine_instantaneous_frequency(f0, f1, rate):
    fs = 20000.0
    x = ex.swept_sine(fs, 3.0, f0, f1, rate=rate)
    assert x.dtype == np.float64 and x.ndim == 1
    assert x.size == round((f1 - f0) / rate * fs)
    assert np.max(np.abs(x)) == pytest.approx(3.0, rel=1e-4)
    tc = _upward_crossings(x, fs)
    # between two upward crossings the phase advances 2 pi: for a linear sweep the mean frequency
    # 1 / dt is exactly the instantaneous frequency at the midpoint
    f_est = 1.0 / np.diff(tc)
    t_mid = 0.5 * (tc[1:] + tc[:-1])
    f_true = f0 + rate * t_mid
    assert np.max(np.abs(f_est - f_true) / f_true) < 2e-4
    assert f_est[-1] > f1 - 2.0  # reaches the end of the band


def test_swept_sine_duration_equivalent_to_rate():
    a = ex.swept_sine(750.0, 1.0, 5.0, 150.0, rate=50.0)
    b = ex.swept_sine(750.0, 1.0, 5.0, 150.0, duration=2.9)
    c = ex.swept_sine(750.0, 1.0, 5.0, 150.0, rate=50.0, duration=2.9)
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(a, c, atol=1e-12)
    p = ex.swept_sine(750.0, 1.0, 5.0, 150.0, rate=50.0, phase=np.pi / 2)
    assert p[0] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "kwargs,name",
    [
        (dict(rate=None, duration=None), "rate"),
        (dict(rate=-1.0), "rate"),
        (dict(duration=0.0), "duration"),
        (dict(rate=53.0, duration=1.0), "duration"),
        (dict(rate=53.0, f1=4.0), "f1"),
        (dict(rate=53.0, f1=400.0), "fs"),
        (dict(rate=53.0, amplitude=-1.0), "amplitude"),
        (dict(rate=53.0, f0=-1.0), "f0"),
        (dict(rate=float("nan")), "rate"),
    ],
)
def test_swept_sine_errors_name_the_argument(kwargs, name):
    args = dict(fs=750.0, amplitude=1.0, f0=5.0, f1=150.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        ex.swept_sine(**args)


def test_sine_frequency_and_errors():
    fs, f = 750.0, 35.59
    x = ex.sine(fs, 2.0, f, 2.0)
    assert x.size == 1500 and x[0] == 0.0
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    peak = np.fft.rfftfreq(x.size, 1 / fs)[np.argmax(spec)]
    assert abs(peak - f) <= fs / x.size
    with pytest.raises(ValueError, match="freq"):
        ex.sine(fs, 1.0, 400.0, 1.0)
    with pytest.raises(ValueError, match="duration"):
        ex.sine(fs, 1.0, 10.0, -1.0)


def test_multisine_spectrum_band_flat_and_rms():
    fs, f0, f1, n = 750.0, 5.0, 150.0, 8192
    x = ex.multisine(fs, 50.0, f0, f1, n, n_periods=3, seed=1)
    assert x.dtype == np.float64 and x.shape == (3 * n,)
    np.testing.assert_array_equal(x[:n], x[n : 2 * n])
    period = x[:n]
    assert np.sqrt(np.mean(period**2)) == pytest.approx(50.0, rel=1e-12)
    freqs, k = ex.multisine_lines(fs, f0, f1, n, return_index=True)
    assert freqs.min() >= f0 and freqs.max() <= f1
    assert freqs.min() - fs / n < f0 and freqs.max() + fs / n > f1  # every line of the band
    amp = np.abs(np.fft.rfft(period))
    assert amp[k].max() / amp[k].min() == pytest.approx(1.0, abs=1e-9)
    off = np.ones(amp.size, bool)
    off[k] = False
    assert np.sum(amp[off] ** 2) < 1e-20 * np.sum(amp[k] ** 2)


def test_multisine_seeds():
    a = ex.multisine(750.0, 1.0, 5.0, 150.0, 1024, seed=3)
    b = ex.multisine(750.0, 1.0, 5.0, 150.0, 1024, seed=3)
    c = ex.multisine(750.0, 1.0, 5.0, 150.0, 1024, seed=4)
    np.testing.assert_array_equal(a, b)
    _, k = ex.multisine_lines(750.0, 5.0, 150.0, 1024, return_index=True)
    pa = np.angle(np.fft.rfft(a)[k])
    pc = np.angle(np.fft.rfft(c)[k])
    assert np.mean(np.abs(np.angle(np.exp(1j * (pa - pc))))) > 0.5  # phases differ
    r = ex.multisine(750.0, None, 5.0, 150.0, 1024, seed=3, rms=1.0)
    np.testing.assert_array_equal(a, r)
    with pytest.raises(ValueError, match="rms"):
        ex.multisine(750.0, 1.0, 5.0, 150.0, 1024, rms=2.0)
    with pytest.raises(ValueError, match="n_per_period"):
        ex.multisine(750.0, 1.0, 5.0, 150.0, 1.5)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(64, 4096),
    fs=st.floats(100.0, 5000.0),
    lo=st.floats(0.0, 0.2),
    width=st.floats(0.05, 0.25),
    seed=st.integers(0, 2**32 - 1),
)
def test_multisine_property_energy_only_on_band_lines(n, fs, lo, width, seed):
    f0, f1 = lo * fs, (lo + width) * fs
    try:
        freqs, k = ex.multisine_lines(fs, f0, f1, n, return_index=True)
    except ValueError:
        return  # no line in the band: documented error
    x = ex.multisine(fs, 2.0, f0, f1, n, seed=seed)
    amp = np.abs(np.fft.rfft(x))
    assert np.all((freqs >= f0 - 1e-9) & (freqs <= f1 + 1e-9)) and np.all(k >= 1)
    off = np.ones(amp.size, bool)
    off[k] = False
    assert np.sum(amp[off] ** 2) <= 1e-20 * np.sum(amp**2)
    assert np.sqrt(np.mean(x**2)) == pytest.approx(2.0, rel=1e-9)


def test_band_limited_noise_rms_band_and_seed():
    fs, f0, f1 = 1024.0, 10.0, 110.0
    x = ex.band_limited_noise(fs, 16.0, f0, f1, 0.3, seed=7)
    assert x.dtype == np.float64 and x.shape == (16384,)
    assert np.sqrt(np.mean(x**2)) == pytest.approx(0.3, rel=1e-12)
    f = np.fft.rfftfreq(x.size, 1 / fs)
    p = np.abs(np.fft.rfft(x)) ** 2
    inband = (f >= f0) & (f <= f1)
    assert p[~inband].sum() < 1e-20 * p.sum()
    # roughly white inside the band: the two halves carry similar energy
    mid = 0.5 * (f0 + f1)
    lo, hi = p[inband & (f < mid)].sum(), p[inband & (f >= mid)].sum()
    assert 0.8 < lo / hi < 1.25
    np.testing.assert_array_equal(x, ex.band_limited_noise(fs, 16.0, f0, f1, 0.3, seed=7))
    assert not np.allclose(x, ex.band_limited_noise(fs, 16.0, f0, f1, 0.3, seed=8))
    with pytest.raises(ValueError, match="rms"):
        ex.band_limited_noise(fs, 1.0, f0, f1, -0.1)


def test_time_axis():
    t = ex.time_axis(750.0, 4)
    np.testing.assert_allclose(t, [0, 1 / 750, 2 / 750, 3 / 750])
    assert ex.n_samples(750.0, 2.0) == 1500
