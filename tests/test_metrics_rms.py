"""model.metrics.rms and what rests on it (fit %, RMSE, the novelty score): the plain formulas' numbers, and a
number, not an overflow, for samples whose squares leave the double range."""
import math

import numpy as np
import pytest

from gpnarx.model.metrics import fit_percent, rms, rmse
from gpnarx.model.novelty import novelty_score


def test_rms_equals_the_plain_formula_on_ordinary_data():
    a = np.random.default_rng(0).normal(size=4097) * 3.0
    assert rms(a) == pytest.approx(float(np.sqrt(np.mean(a * a))), rel=1e-14)
    b = a + 0.1 * np.random.default_rng(1).normal(size=a.size)
    assert fit_percent(a, b) == pytest.approx(100 * (1 - np.sqrt(np.sum((a - b) ** 2) / np.sum(a * a))), rel=1e-13)
    assert rmse(a, b) == pytest.approx(float(np.sqrt(np.mean((a - b) ** 2))), rel=1e-14)


def test_rms_of_samples_beyond_the_square_range_is_finite():
    a = np.zeros(100)
    a[7] = 1e200
    assert rms(a) == pytest.approx(1e199, rel=1e-14)
    assert rms(np.full(3, 1e-200)) == pytest.approx(1e-200, rel=1e-14)  # no underflow either
    assert rms([]) != rms([])  # nan
    assert rms([0.0, 0.0]) == 0.0
    assert math.isinf(rms([1.0, np.inf]))


def test_novelty_score_of_a_huge_spike_is_a_number():
    y = np.zeros(512)
    y[100] = 1e160
    out = novelty_score(y, np.zeros(512), np.full(512, 1e-3))
    assert math.isfinite(out["score"]) and out["score"] == pytest.approx(1e163 / math.sqrt(512), rel=1e-12)
    assert math.isinf(out["nlpd"])  # its z^2 term leaves the double range: null in JSON (schema: nullable)
