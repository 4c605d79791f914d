"""Bouc-Wen benchmark simulator: physics, convergence, steady state, speed."""
import time
from pathlib import Path

import numpy as np
import pytest

from gpnarx.training.excitations import sine, swept_sine
from gpnarx.training.simulators.boucwen import BoucWen, compare_to_official, fourier_resample

FS = 750.0
OFFICIAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "boucwen"


def _rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


def _resonance(u, y, fs, f0=5.0, f1=150.0):
    """Frequency [Hz] of the peak of |Y / U| inside the sweep band."""
    f = np.fft.rfftfreq(u.size, 1 / fs)
    h = np.abs(np.fft.rfft(y) / np.fft.rfft(u))
    band = (f > f0) & (f < f1)
    return float(f[band][np.argmax(h[band])])


def test_table1_defaults():
    bw = BoucWen()
    assert (bw.m, bw.c, bw.k, bw.alpha, bw.beta, bw.gamma, bw.delta, bw.nu) == (
        2.0, 10.0, 5e4, 5e4, 1e3, 0.8, -1.1, 1.0)
    assert (bw.fs, bw.substeps) == (750.0, 20)
    assert bw.linear_resonance == pytest.approx(35.59, abs=0.01)


def test_hardening_resonance_shift():
    bw = BoucWen()
    peaks = {}
    for a in (10.0, 80.0):
        u = swept_sine(FS, a, 5.0, 150.0, rate=53.0)
        peaks[a] = _resonance(u, bw.simulate(u)["y"], FS)
    print(f"resonance peak |Y/U|: 10 N {peaks[10.0]:.2f} Hz, 80 N {peaks[80.0]:.2f} Hz")
    assert 35.0 < peaks[10.0] < 39.0  # near the linear resonance (35.59 Hz, shifted by the sweep)
    assert peaks[80.0] > peaks[10.0] + 3.0  # gamma + delta < 0: hardening


def test_step_halving_changes_output_below_1e8_m():
    u = swept_sine(FS, 50.0, 5.0, 150.0, rate=53.0)
    y20 = BoucWen().simulate(u)["y"]
    y40 = BoucWen(substeps=40).simulate(u)["y"]
    d = _rms(y20 - y40)
    print(f"50 N sweep: RMS(y) = {_rms(y20):.3e} m, step-halving difference {d:.2e} m RMS")
    assert _rms(y20) > 1e-4
    assert d < 1e-8


def test_linear_limit_matches_analytic_frf():
    """beta = 0 makes z = alpha y: a linear oscillator with stiffness k + alpha."""
    bw = BoucWen(beta=0.0)
    n, cycles, a = 750, 30, 10.0  # 30 Hz, an integer number of cycles per period
    f = cycles * FS / n
    u = sine(FS, a, f, n / FS)
    out = bw.simulate(u, periodic=True)
    w = 2 * np.pi * f
    h = 1.0 / (bw.k + bw.alpha - bw.m * w**2 + 1j * bw.c * w)
    t = np.arange(n) / FS
    y_ref = a * np.abs(h) * np.sin(w * t + np.angle(h))
    assert _rms(out["y"] - y_ref) < 1e-8 * _rms(y_ref)  # RK4 error at 15 kHz: ~2e-9
    np.testing.assert_allclose(out["z"], bw.alpha * out["y"], atol=1e-9 * np.max(np.abs(out["z"])))
    np.testing.assert_allclose(out["v"], a * np.abs(h) * w * np.cos(w * t + np.angle(h)), atol=1e-8 * a * np.abs(h) * w)


def test_periodic_sine_reaches_steady_state():
    bw = BoucWen()
    u = sine(FS, 50.0, 36.0, 0.5)  # 18 whole cycles in 375 samples
    p = bw.default_n_periods(u.size)
    assert (p - 1) * u.size / FS >= bw.settle_time
    last = bw.simulate(u, periodic=True)["y"]
    one_more = bw.simulate(u, periodic=True, n_periods=p + 1)["y"]
    first = bw.simulate(u, periodic=True, n_periods=1)["y"]
    assert _rms(last - one_more) < 1e-12  # the last two periods agree
    assert _rms(last - first) > 1e-6  # ... while the first period from rest is still a transient
    assert _rms(last) > 1e-4


def test_hysteresis_loop_opens_with_amplitude():
    """Area of the z-y loop per cycle (dissipated energy) grows faster than amplitude squared."""
    bw = BoucWen()
    u1 = sine(FS, 10.0, 36.0, 0.5)
    areas = []
    for a in (10.0, 80.0):
        out = bw.simulate(u1 * a / 10.0, periodic=True)
        y, z = out["y"], out["z"]
        area = abs(np.sum(0.5 * (z[1:] + z[:-1]) * np.diff(y)))
        areas.append(area / np.ptp(y) ** 2)
    assert areas[1] > 2.0 * areas[0]


def test_non_periodic_starts_from_rest_and_2d_input():
    bw = BoucWen()
    u = swept_sine(FS, 10.0, 5.0, 150.0, rate=53.0)[:300]
    out = bw.simulate(u)
    assert out["y"][0] == 0.0 and out["v"][0] == 0.0 and out["z"][0] == 0.0
    assert set(out) >= {"y", "v", "z"} and out["y"].dtype == np.float64 and out["y"].shape == u.shape
    both = bw.simulate(np.stack([u, 2 * u]))
    assert both["y"].shape == (2, u.size)
    np.testing.assert_array_equal(both["y"][0], out["y"])
    with pytest.raises(ValueError, match="u"):
        bw.simulate(np.array([1.0, np.nan, 2.0]))
    with pytest.raises(ValueError, match="n_periods"):
        bw.simulate(u, n_periods=3)
    with pytest.raises(ValueError, match="substeps"):
        BoucWen(substeps=0)


def test_progress_callback_counts_all_samples():
    bw = BoucWen()
    u = sine(FS, 1.0, 36.0, 0.5)
    seen = []
    bw.simulate(u, periodic=True, n_periods=3, callback=seen.append)
    assert sum(seen) == 3 * u.size


def test_fourier_resample_is_exact_interpolant():
    n = 64
    k = np.arange(n)
    x = np.sin(2 * np.pi * 5 * k / n) + 0.3 * np.cos(2 * np.pi * 11 * k / n)
    up = fourier_resample(x, 8 * n)
    t = np.arange(8 * n) / 8
    np.testing.assert_allclose(up, np.sin(2 * np.pi * 5 * t / n) + 0.3 * np.cos(2 * np.pi * 11 * t / n), atol=1e-12)


def test_two_second_record_is_fast():
    bw = BoucWen()
    u = swept_sine(FS, 50.0, 5.0, 150.0, rate=53.0)[:1500]
    bw.simulate(u[:50])  # warm-up
    t0 = time.perf_counter()
    bw.simulate(u)
    dt = time.perf_counter() - t0
    print(f"2 s record (1500 samples, 30000 RK4 sub-steps): {dt:.3f} s")
    assert dt < 3.0  # loose for CI; typically ~0.05 s


@pytest.mark.skipif(not OFFICIAL.is_dir(), reason=f"official Bouc-Wen benchmark files not found at {OFFICIAL}: "
                    "the simulator's agreement with them (< 1e-6 m RMS) is not checked on this machine")
def test_matches_official_benchmark_files():
    diffs = compare_to_official(str(OFFICIAL))
    print("official benchmark RMS differences [m]:", diffs)
    assert diffs and all(d < 1e-6 for d in diffs.values())
