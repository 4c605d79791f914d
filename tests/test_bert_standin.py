"""BERT stand-in: calibration against the real 5 N m records, softening, torque, realizations."""
from __future__ import annotations

import time

import numpy as np
import pytest

from gpnarx.training.datapaths import bert_data_dir
from gpnarx.training.simulators.bert_standin import (
    BertStandin,
    calibration_table,
    format_calibration_table,
    resonance_from_noise,
    steady_amplitude,
)

DATA = bert_data_dir()
needs_data = pytest.mark.skipif(not (DATA / "Sine").is_dir(), reason=f"BERT data not found at {DATA}")
LISTED = [5, 5.5, 6, 6.5, 6.75, 8, 8.5, 9, 9.5, 9.75, 17, 19, 20]


@pytest.fixture(scope="module")
def table():
    return calibration_table(DATA)


@needs_data
def test_velocity_amplitude_within_25_percent_of_the_rig(table):
    assert [round(r["freq"], 2) for r in table] == LISTED
    for r in table:
        assert 0.14 < r["volts"] < 0.16  # the rig's ~0.15 V drive, also used for the stand-in
        assert abs(r["error_pct"]) < 25.0, r
    text = format_calibration_table(table)
    assert text.count("\n") == len(table) + 1


@needs_data
def test_super_harmonics_reproduced(table):
    by_f = {round(r["freq"], 2): r for r in table}
    # the rig: strong 2x super-harmonic of the first mode when 2x drive is near 18.8 Hz
    for f in (9.0, 9.5, 9.75):
        assert by_f[f]["real_h2"] > 0.2
        assert by_f[f]["standin_h2"] > 0.2
        assert by_f[f]["standin_h2"] == pytest.approx(by_f[f]["real_h2"], rel=0.5)
    assert by_f[9.5]["standin_h2"] == max(r["standin_h2"] for r in table)
    # 3x super-harmonic near 6-6.5 Hz (3x drive near resonance): present, above the off-resonance level
    assert by_f[6.0]["standin_h3"] > 2 * by_f[8.0]["standin_h3"]
    assert by_f[6.5]["standin_h3"] > 0.01
    # large-amplitude response near resonance stays nearly harmonic, like the rig
    for f in (17.0, 19.0, 20.0):
        assert by_f[f]["standin_h2"] < 0.02 and by_f[f]["real_h2"] < 0.02


def test_low_amplitude_resonance_near_18p8_hz():
    f = resonance_from_noise(BertStandin(), rms=0.00265, duration=32.0, seed=0)
    assert abs(f - 18.8) < 0.5


def test_softening_resonance_drops_with_amplitude():
    low = resonance_from_noise(BertStandin(), rms=0.003, duration=32.0, seed=1)
    high = resonance_from_noise(BertStandin(), rms=0.3, duration=32.0, seed=1)
    assert high < low - 0.1


def test_torque_changes_the_response():
    m5, m9 = BertStandin(torque=5.0), BertStandin(torque=9.0)
    assert m9.linear_resonance > m5.linear_resonance
    a5 = m5.steady_amplitude(19.0, 0.15, settle=6.0, measure=1.0)
    a9 = m9.steady_amplitude(19.0, 0.15, settle=6.0, measure=1.0)
    # tighter joint: less slip, less softening and friction damping, closer to its resonance at 19 Hz
    assert a9 > 1.3 * a5
    assert steady_amplitude(19.0, 0.15, torque=5.0, settle=6.0, measure=1.0) == pytest.approx(a5)


def test_realizations_seeded():
    u = 0.05 * np.random.default_rng(0).standard_normal(2048)
    a = BertStandin(seed=7).simulate(u)["y"]
    b = BertStandin(seed=7).simulate(u)["y"]
    c = BertStandin(seed=8).simulate(u)["y"]
    nominal = BertStandin().simulate(u)["y"]
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c, rtol=0, atol=1e-4 * np.abs(a).max())
    assert not np.allclose(a, nominal, rtol=0, atol=1e-4 * np.abs(a).max())
    np.testing.assert_array_equal(nominal, BertStandin(seed=None).simulate(u)["y"])
    p7, p8 = BertStandin(seed=7).params, BertStandin(seed=8).params
    assert abs(p7.f_stuck / p8.f_stuck - 1) < 0.003  # calibrated scatter: 0.04 % on the frequency


def test_scatter_multiplies_the_log_deviations():
    nominal = BertStandin().params
    one, ten = BertStandin(seed=3).params, BertStandin(seed=3, scatter=10).params
    for name in ("f_stuck", "zeta_v", "gain", "c_even"):
        d1 = np.log(getattr(one, name) / getattr(nominal, name))
        d10 = np.log(getattr(ten, name) / getattr(nominal, name))
        assert d1 != 0.0 and d10 == pytest.approx(10 * d1, rel=1e-9)
    np.testing.assert_allclose(np.log(np.divide(ten.slip, nominal.slip)),
                               10 * np.log(np.divide(one.slip, nominal.slip)))
    assert BertStandin(seed=3, scatter=0).params == nominal
    assert BertStandin(seed=None, scatter=10).params == nominal
    for bad in (-1, 101, float("nan"), "x"):
        with pytest.raises(ValueError, match="scatter"):
            BertStandin(seed=3, scatter=bad)


def test_simulate_outputs_and_speed():
    fs = 1024.0
    t = np.arange(16384) / fs
    u = 0.1 * np.sin(2 * np.pi * 5 * t * t / 16)  # slow chirp
    sim = BertStandin()
    t0 = time.perf_counter()
    out = sim.simulate(u, fs=fs)
    elapsed = time.perf_counter() - t0
    assert set(out) >= {"y", "x", "z", "u", "fs"}
    for k in ("y", "x", "z"):
        assert out[k].shape == u.shape and out[k].dtype == np.float64 and np.all(np.isfinite(out[k]))
    assert elapsed < 3.0  # ~0.3 s on a laptop-class core
    # velocity is the derivative of displacement
    dx = np.gradient(out["x"], 1 / fs)
    assert np.max(np.abs(dx[10:-10] - out["y"][10:-10])) < 0.02 * np.max(np.abs(out["y"]))
    assert sim.units == {"u": "V", "y": "m/s", "x": "m", "z": "N"} and sim.fs == 1024.0
    assert sim.input_gain == pytest.approx(sim.params.gain * sim.modal_mass)


def test_invalid_arguments():
    with pytest.raises(ValueError, match="torque"):
        BertStandin(torque=-1)
    with pytest.raises(ValueError, match="NaN"):
        BertStandin().simulate(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match="1-D"):
        BertStandin().simulate(np.zeros((2, 3)))


def test_scatter_calibration_against_the_papers_lag_surface_fit():
    """The calibrated scatter lets the nominal stand-in predict its own 0.10 V sweep realizations at
    about the paper's lag-surface fit (96.1 %); the former 10x scatter could not (docstring figures
    over 24 realizations: median 96.4 % vs 66.0 %)."""
    from gpnarx.model.metrics import fit_percent
    from gpnarx.training.config import simulate_record

    u = simulate_record({"system": "bert-standin", "excitation": "sweep", "amplitude": 0.10}).u
    nominal = BertStandin().simulate(u)["y"]
    fits = {k: [fit_percent(BertStandin(seed=s, scatter=k).simulate(u)["y"], nominal) for s in range(1, 7)]
            for k in (1.0, 10.0)}
    assert np.median(fits[1.0]) > 93.0
    assert np.median(fits[10.0]) < 85.0
