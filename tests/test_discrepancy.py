"""The free-run band's model-discrepancy term (model.discrepancy) and its held-out calibration."""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.model.discrepancy import SCALE_GRID, calibrate_scale, check_discrepancy, local_amplitude, widen
from gpnarx.model.freerun import FreeRun
from gpnarx.storage.bundle import load_bundle, save_bundle

FS = 1000.0


def _sine_run(amp=2.0, n=4000, floor=0.01, f=10.0):
    t = np.arange(n) / FS
    mean = amp * np.sin(2 * np.pi * f * t)
    std = np.full(n, floor)
    return FreeRun(mean, std, mean - 2.5758 * std, mean + 2.5758 * std, 0.99, 0, "linear",
                   latent_lower=mean - 2.0 * std, latent_upper=mean + 2.0 * std)


def test_local_amplitude_of_a_sine_is_its_rms():
    run = _sine_run(amp=2.0)
    a = local_amplitude(run.mean, 500)  # five periods of 10 Hz at 1 kHz
    assert np.allclose(a[500:-500], 2.0 / np.sqrt(2), rtol=1e-3)


def test_widen_adds_the_term_in_quadrature_to_std_and_both_bands():
    run = _sine_run()
    assert widen(run, 0.0, 100) is run
    w = widen(run, 0.05, 100)
    a = local_amplitude(run.mean, 100)
    assert np.allclose(w.std, np.sqrt(run.std**2 + (0.05 * a) ** 2))
    half = np.sqrt((2.5758 * run.std) ** 2 + (2.5758 * 0.05 * a) ** 2)
    assert np.allclose(w.upper - w.mean, half, rtol=1e-4) and np.allclose(w.mean - w.lower, half, rtol=1e-4)
    lat = np.sqrt((2.0 * run.std) ** 2 + (2.5758 * 0.05 * a) ** 2)
    assert np.allclose(w.latent_upper - w.mean, lat, rtol=1e-4)
    assert np.array_equal(w.mean, run.mean)


def test_calibration_finds_the_smallest_scale_that_covers_every_record():
    rng = np.random.default_rng(3)
    runs = []
    for k, amp in enumerate((1.0, 3.0)):
        run = _sine_run(amp=amp, floor=1e-4)
        a = local_amplitude(run.mean, 250)
        y = run.mean + 0.05 * a * rng.standard_normal(run.mean.size)  # a 5 % model error
        runs.append((f"r{k}", y, run, 0))
    d = calibrate_scale(runs, 250)
    assert d["reached"] and d["target"] == 0.99
    assert 0.04 <= d["scale"] <= 0.07
    assert min(d["coverage_after"].values()) >= 0.99 and max(d["coverage_before"].values()) < 0.5
    i = int(np.searchsorted(SCALE_GRID, d["scale"]))
    smaller = SCALE_GRID[i - 1]  # the grid's previous value falls short on at least one record
    from gpnarx.model.discrepancy import coverage_at
    assert min(coverage_at(y, r, smaller, 250, s) for _, y, r, s in runs) < 0.99


def test_calibration_that_cannot_reach_the_target_says_so():
    run = _sine_run(amp=1e-6, floor=1e-9)
    y = run.mean + 1.0  # an offset no amplitude-proportional term can cover
    d = calibrate_scale([("off", y, run, 0)], 100)
    assert d["reached"] is False and d["scale"] == SCALE_GRID[-1] and d["coverage_after"]["off"] < 0.99


@pytest.mark.parametrize("bad", [{"scale": -1, "window": 10}, {"scale": 0.1, "window": 0},
                                 {"scale": float("nan"), "window": 10}, {"scale": 0.1, "window": 2.5}, "x"])
def test_bad_stored_discrepancy_is_refused(bad):
    with pytest.raises(ValueError, match="band_discrepancy"):
        check_discrepancy(bad)


def test_the_window_kind_is_stored_and_a_bundle_without_one_is_centred():
    from gpnarx.model.discrepancy import window_kind

    assert window_kind(check_discrepancy({"scale": 0.1, "window": 10})) == "centred"  # bundles before the choice
    assert window_kind(check_discrepancy({"scale": 0.1, "window": 10, "window_kind": "trailing"})) == "trailing"
    with pytest.raises(ValueError, match="band_discrepancy.window_kind"):
        check_discrepancy({"scale": 0.1, "window": 10, "window_kind": "ahead"})
    run = _sine_run(amp=1.0)
    d = calibrate_scale([("s", run.mean + 0.02 * np.sin(np.arange(run.mean.size)), run, 0)], 100, kind="trailing")
    assert d["window_kind"] == "trailing" and d["reached"]


def test_a_trailing_amplitude_sees_only_the_past():
    m = np.random.default_rng(2).normal(size=500)
    a = local_amplitude(m, 50, kind="trailing")
    ref = [np.sqrt(np.mean(np.concatenate([np.full(max(0, 49 - i), m[0]), m[max(0, i - 49): i + 1]]) ** 2))
           for i in range(m.size)]
    assert np.allclose(a, ref, rtol=1e-12)
    cut = m.copy()
    cut[300:] = 0.0  # the future changes: the amplitude up to it does not
    assert np.array_equal(local_amplitude(cut, 50, kind="trailing")[:300], a[:300])
    assert not np.array_equal(local_amplitude(cut, 50)[:300], local_amplitude(m, 50)[:300])  # the centred one does


def test_model_calibrates_on_held_out_records_and_the_bundle_keeps_it(sdof_model, sdof_data, tmp_path):
    from conftest import sdof_simulate

    model = sdof_model
    rng = np.random.default_rng(7)
    u = rng.normal(size=1200)
    y = 1.1 * sdof_simulate(u)  # a structure 10 % stiffer in gain than the model knows: model-form error
    before = model.simulate(u, method="linear")
    try:
        d = model.calibrate_band([("held", u, y, "rest")], window=100)
        assert d["records"] == ["held"] and d["calibration_method"] == "linear"
        assert d["coverage_before"]["held"] < 0.99 <= d["coverage_after"]["held"] and d["scale"] > 0
        after = model.simulate(u, method="linear")
        assert np.array_equal(after.mean, before.mean) and np.all(after.std >= before.std)
        cov = np.mean((y >= after.lower) & (y <= after.upper))
        assert cov == pytest.approx(d["coverage_after"]["held"])
        path = save_bundle(model, tmp_path, "sdof", fs=500.0, units={"u": "N", "y": "m"})
        back = load_bundle(path).model
        assert back.band_discrepancy_["scale"] == d["scale"] and back.band_discrepancy_["window_kind"] == "centred"
        assert np.allclose(back.simulate(u, method="linear").upper, after.upper)
        with pytest.raises(ValueError, match="start"):
            model.calibrate_band([("bad", u, y, "sometime")], window=100)
    finally:
        model.band_discrepancy_ = None  # the session fixture is shared


def test_held_amplitude_is_the_decaying_peak_hold_and_continues_across_chunks():
    from gpnarx.model.discrepancy import held_amplitude

    a = np.abs(np.random.default_rng(4).normal(size=3000))
    a[800:900] *= 40.0  # a large response, then a small one
    h = held_amplitude(a, 250.0)
    ref, cur = np.empty_like(a), 0.0
    for i, v in enumerate(a):  # the recursion itself
        cur = max(v, cur * np.exp(-1.0 / 250.0))
        ref[i] = cur
    assert np.allclose(h, ref, rtol=1e-12)
    assert np.all(h >= a * (1 - 1e-12)) and h[1400] > 2.0 * a[1000:].max()  # the burst still held 500 samples on
    first = held_amplitude(a[:1234], 250.0)
    assert np.allclose(np.concatenate([first, held_amplitude(a[1234:], 250.0, start=first[-1])]), h, rtol=1e-12)
    assert np.array_equal(held_amplitude(a, 0), a)


def test_a_hold_covers_a_decay_the_mean_underestimates_with_a_smaller_scale():
    # after a burst the measured output decays slower than the predicted mean: the error outlives the
    # response that caused it. Without a hold only a large scale covers it; with one a small scale does.
    n = 6000
    t = np.arange(n) / FS
    env_model = np.where(t < 2.0, 1.0, np.exp(-(t - 2.0) / 0.1))
    env_real = np.where(t < 2.0, 1.0, np.exp(-(t - 2.0) / 0.4))
    mean = env_model * np.sin(2 * np.pi * 20.0 * t)
    y = env_real * np.sin(2 * np.pi * 20.0 * t)
    std = np.full(n, 1e-4)
    run = FreeRun(mean, std, mean - 2.5758 * std, mean + 2.5758 * std, 0.99, 0, "linear")
    plain = calibrate_scale([("decay", y, run, 0)], 100)
    held = calibrate_scale([("decay", y, run, 0)], 100, hold=int(0.5 * FS))
    assert held["reached"] and held["hold"] == 500 and held["scale"] < plain["scale"]
    assert check_discrepancy(held)["hold"] == 500
    with pytest.raises(ValueError, match="band_discrepancy.hold"):
        check_discrepancy({"scale": 0.1, "window": 10, "hold": -3})


def test_a_held_trailing_band_in_chunks_is_the_whole_records_band(sdof_model, sdof_data):
    from gpnarx.operations.stream_token import decode_state, encode_state

    model, u = sdof_model, sdof_data["u2"][:1200]
    model.band_discrepancy_ = {"scale": 0.2, "window": 50, "window_kind": "trailing", "hold": 120}
    try:
        whole = model.simulate(u, method="linear")
        parts, state = [], None
        for a in range(0, u.size, 250):
            run = model.simulate(u[a: a + 250], method="linear", state=state, open_end=a + 250 < u.size)
            state = decode_state(encode_state(run.state, "m", "1"), "m", "1")  # through a token, as served
            assert state.amp_hold is not None and state.amp_hold.size == 1
            parts.append(run)
        for key in ("mean", "std", "lower", "upper"):
            chunked = np.concatenate([getattr(p, key) for p in parts])
            assert np.allclose(chunked, getattr(whole, key), rtol=1e-9, atol=1e-12), key
    finally:
        model.band_discrepancy_ = None  # the session fixture is shared


def test_gp_scale_multiplies_the_propagated_band_before_the_term():
    run = _sine_run(floor=0.02)
    w = widen(run, 0.05, 100, gp_scale=0.5)
    a = local_amplitude(run.mean, 100)
    assert np.allclose(w.std, np.sqrt((0.5 * run.std) ** 2 + (0.05 * a) ** 2))
    half = np.sqrt((0.5 * 2.5758 * run.std) ** 2 + (2.5758 * 0.05 * a) ** 2)
    assert np.allclose(w.upper - w.mean, half, rtol=1e-4) and np.allclose(w.mean - w.lower, half, rtol=1e-4)
    only = widen(run, 0.0, 100, gp_scale=0.5)  # no term: the propagated band alone, halved
    assert np.allclose(only.upper - only.mean, 0.5 * (run.upper - run.mean))
    assert np.allclose(only.latent_upper - only.mean, 0.5 * (run.latent_upper - run.mean))
    assert widen(run, 0.0, 100, gp_scale=1.0) is run
    assert check_discrepancy({"scale": 0.1, "window": 10, "gp_scale": 0.3})["gp_scale"] == 0.3
    for bad in (0.0, -1.0, float("inf"), True, "x"):
        with pytest.raises(ValueError, match="band_discrepancy.gp_scale"):
            check_discrepancy({"scale": 0.1, "window": 10, "gp_scale": bad})


def test_band_tightness_is_the_share_of_the_band_a_record_needs():
    from gpnarx.model.discrepancy import band_tightness

    run = _sine_run(floor=0.01)
    hw = 2.5758 * 0.01
    y = run.mean + 0.5 * hw * np.sign(np.sin(np.arange(run.mean.size)))  # every error half the half-width
    assert band_tightness(y, run) == pytest.approx(0.5)
    assert band_tightness(run.mean + 2 * hw, run) == pytest.approx(2.0)  # not covered: above 1


def test_a_calibrated_gp_scale_shrinks_a_propagated_band_too_wide_for_quiet_records():
    """Two records: a loud one whose error grows with the amplitude, a quiet one whose propagated band is
    four times its error. The fixed factor covers both with the amplitude term alone on top of a band far
    too wide for the quiet record; calibrated, the factor falls and the quiet record's band tightens, both
    still covered."""
    from gpnarx.model.discrepancy import GP_SCALE_GRID, band_tightness

    rng = np.random.default_rng(5)
    loud = _sine_run(amp=2.0, floor=0.01)
    y_loud = loud.mean + 0.05 * local_amplitude(loud.mean, 250) * rng.standard_normal(loud.mean.size)
    quiet = _sine_run(amp=0.01, floor=0.01)
    y_quiet = quiet.mean + 0.0025 * rng.standard_normal(quiet.mean.size)
    runs = [("loud", y_loud, loud, 0), ("quiet", y_quiet, quiet, 0)]
    fixed = calibrate_scale(runs, 250)
    cal = calibrate_scale(runs, 250, gp_scales=GP_SCALE_GRID)
    assert fixed["gp_scale"] == 1.0 and "tightness_after" not in fixed
    assert cal["reached"] and min(cal["coverage_after"].values()) >= 0.99
    assert cal["gp_scale"] < 0.6
    t_fixed = band_tightness(y_quiet, widen(quiet, fixed["scale"], 250))
    t_cal = band_tightness(y_quiet, widen(quiet, cal["scale"], 250, gp_scale=cal["gp_scale"]))
    assert t_fixed < 0.4 and t_cal > 1.5 * t_fixed
    assert min(cal["tightness_after"].values()) == pytest.approx(min(t_cal, band_tightness(
        y_loud, widen(loud, cal["scale"], 250, gp_scale=cal["gp_scale"]))))
    with pytest.raises(ValueError, match="gp_scales"):
        calibrate_scale(runs, 250, gp_scales=[0.0])


def test_a_calibrated_gp_scale_is_stored_and_used_by_the_model(sdof_model, tmp_path):
    model = sdof_model
    rng = np.random.default_rng(8)
    u = rng.normal(size=800)
    try:
        base = model.simulate(u, method="linear")
        model.band_discrepancy_ = check_discrepancy({"scale": 0.0, "window": 50, "gp_scale": 0.5})
        half = model.simulate(u, method="linear")
        assert np.allclose(half.upper - half.mean, 0.5 * (base.upper - base.mean))
        path = save_bundle(model, tmp_path, "sdof", fs=500.0, units={"u": "N", "y": "m"})
        assert load_bundle(path).model.band_discrepancy_["gp_scale"] == 0.5
    finally:
        model.band_discrepancy_ = None  # the session fixture is shared
