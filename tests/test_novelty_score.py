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
