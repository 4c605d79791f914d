"""Novelty score methods (model.novelty): the RMS score and its spike-robust segment-median variant."""
import numpy as np
import pytest

from gpnarx.model.novelty import RMS_METHOD, SEGMENT_METHOD, SEGMENTS, method_of, novelty_score


def _healthy(n=2048, seed=0):
    rng = np.random.default_rng(seed)
    mean = np.sin(np.linspace(0, 40, n))
    std = np.full(n, 0.1)
    return mean + std * rng.standard_normal(n), mean, std


def test_both_scores_are_about_one_on_a_healthy_record():
    y, mean, std = _healthy()
    for method in (RMS_METHOD, SEGMENT_METHOD):
        out = novelty_score(y, mean, std, method)
        assert out["method"] == method and out["score"] == pytest.approx(1.0, abs=0.1)


def test_isolated_spikes_lift_the_rms_score_but_not_the_segment_median():
    y, mean, std = _healthy()
    y[[100, 900, 1500]] += 40 * std[0]  # three dropout-like spikes, 40 sigma each
    rms = novelty_score(y, mean, std, RMS_METHOD)["score"]
    seg = novelty_score(y, mean, std, SEGMENT_METHOD)["score"]
    assert rms > 1.5  # sqrt(1 + 3 * 1600 / 2048) ~ 1.8
    assert seg == pytest.approx(1.0, abs=0.15)


def test_a_persistent_change_lifts_both_scores():
    y, mean, std = _healthy()
    y = y + 3 * std[0] * np.sin(np.linspace(0, 80, y.size))  # a model mismatch over the whole record
    for method in (RMS_METHOD, SEGMENT_METHOD):
        assert novelty_score(y, mean, std, method)["score"] > 1.8, method


def test_bad_method_and_too_short_records_are_refused():
    y, mean, std = _healthy(n=SEGMENTS - 1)
    with pytest.raises(ValueError, match="needs at least 16 scored samples, got 15"):
        novelty_score(y, mean, std, SEGMENT_METHOD)
    assert novelty_score(y, mean, std)["score"] > 0  # the RMS score has no such floor
    with pytest.raises(ValueError, match="novelty method must be one of"):
        novelty_score(y, mean, std, "max")


def test_method_of_a_bundle_calibration():
    assert method_of(None) == RMS_METHOD and method_of({"threshold": 1.0}) == RMS_METHOD  # older bundles
    assert method_of({"method": SEGMENT_METHOD}) == SEGMENT_METHOD


def test_healthy_records_scored_at_once_give_the_scores_of_one_at_a_time():
    """training.novelty_calibration.score_healthy(jobs=2) scores records in forked processes (how the default
    build calibrates bert-real-monitor on 2 cores): the same scores as one at a time, in record order."""
    from test_service_support import FS, built_registry, short_record

    from gpnarx.model.record import Record
    from gpnarx.storage.bundle import load_bundle
    from gpnarx.training.novelty_calibration import score_healthy

    bundle = load_bundle(built_registry().root / "plain" / "1")
    recs = []
    for k in range(3):
        u, y = short_record(200 + 20 * k)
        recs.append(Record(u, y, FS, name=f"r{k}"))
    one = score_healthy(bundle, recs, RMS_METHOD, n_paths=8, seed=3, jobs=1)
    two = score_healthy(bundle, recs, RMS_METHOD, n_paths=8, seed=3, jobs=2)
    assert [r["name"] for r in two] == ["r0", "r1", "r2"] and two == one
    with pytest.raises(ValueError, match="r0: a healthy record needs its measured output y"):
        score_healthy(bundle, [Record(recs[0].u, None, FS, name="r0"), recs[1]], RMS_METHOD, n_paths=8, jobs=2)


def test_healthy_records_scored_at_once_never_fork_a_process_with_jax_running():
    """With JAX's runtime started in this process (its threads: a fork may deadlock, and JAX warns on
    ``os.fork()``), ``score_healthy(jobs=2)`` starts its scorers without forking this process: no warning,
    the same scores as one at a time."""
    import warnings

    jnp = pytest.importorskip("jax.numpy")
    from test_service_support import FS, built_registry, short_record

    from gpnarx.model.record import Record
    from gpnarx.storage.bundle import load_bundle
    from gpnarx.training.novelty_calibration import score_healthy

    float(jnp.zeros(1).sum())  # JAX's backend up, its at-fork warning installed
    bundle = load_bundle(built_registry().root / "plain" / "1")
    recs = [Record(*short_record(150 + 10 * k), FS, name=f"r{k}") for k in range(2)]
    one = score_healthy(bundle, recs, RMS_METHOD, n_paths=8, seed=3, jobs=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        two = score_healthy(bundle, recs, RMS_METHOD, n_paths=8, seed=3, jobs=2)
    assert two == one
    assert not [w for w in caught if "fork" in str(w.message)], [str(w.message) for w in caught]


def test_grouped_calibration_takes_the_spread_between_recordings():
    """Windows of two recordings at different score levels (tight within each): the pooled fit sees 20 close draws
    per level, the grouped fit (``groups``) a spread between recordings, and places the threshold for a new
    recording's window: exp(mu + z sd), sd^2 = between^2 (1 + 1/G) + within^2."""
    from scipy.special import ndtri

    from gpnarx.model.novelty import calibrate_threshold

    rng = np.random.default_rng(0)
    levels = {"a": 0.1, "b": 0.14, "c": 0.4}
    scores, groups = [], []
    for g, level in levels.items():
        scores += list(level * np.exp(0.05 * rng.standard_normal(20)))
        groups += [g] * 20
    pooled = calibrate_threshold(scores, 0.01)
    grouped = calibrate_threshold(scores, 0.01, groups=groups)
    logs = np.log(scores).reshape(3, 20)
    within = logs.var(axis=1, ddof=1).mean()
    between = logs.mean(axis=1).var(ddof=1) - within / 20
    sd = np.sqrt(between * (1 + 1 / 3) + within)
    assert grouped["n_groups"] == 3 and grouped["log_std"] == pytest.approx(sd)
    assert grouped["log_std_within"] == pytest.approx(np.sqrt(within))
    assert grouped["threshold"] == pytest.approx(np.exp(logs.mean() + ndtri(0.99) * sd))
    assert grouped["threshold"] > pooled["threshold"] and "n_groups" not in pooled
    # one group: nothing between recordings to measure, the pooled fit
    assert calibrate_threshold(scores, 0.01, groups=["x"] * 60) == pooled
    with pytest.raises(ValueError, match="one label per healthy score"):
        calibrate_threshold(scores, 0.01, groups=["a", "b"])


def test_probe_contract_spans_the_calibrated_drives_and_no_more():
    """Calibrated on 5, 5.5 and 9.75 Hz sines, the probe is the middle of that range with half of it as tolerance
    (a median centre would reach down to 0.75 Hz below the lowest drive)."""
    from gpnarx.model.probe import probe_check, probe_contract

    fs = 1024.0
    t = np.arange(2048) / fs
    sines = [0.15 * np.sin(2 * np.pi * f * t) for f in (5.0, 5.5, 9.75)]
    probe = probe_contract(sines, fs)
    assert probe["frequency"] == pytest.approx(7.375, abs=0.01)
    assert probe["frequency_tolerance"] == pytest.approx(2.375, abs=0.01)
    assert probe_check(0.15 * np.sin(2 * np.pi * 9.0 * t), fs, probe, "measured")["probe_match"] is True
    for f in (4.25, 17.0):
        assert probe_check(0.15 * np.sin(2 * np.pi * f * t), fs, probe, "measured")["probe_match"] is False
