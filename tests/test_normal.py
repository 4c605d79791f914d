"""model.normal: the standard normal quantiles every band and threshold uses, against scipy's."""
import numpy as np
import pytest
from scipy.special import ndtri

from gpnarx.model.normal import band_z, quantile


def test_quantile_matches_scipy_over_the_whole_range():
    p = np.concatenate([np.geomspace(1e-300, 0.5, 400), 1.0 - np.geomspace(1e-16, 0.5, 400)])
    ours = np.array([quantile(v) for v in p])
    ref = ndtri(p)
    assert np.all(np.abs(ours - ref) <= 4e-15 * np.maximum(1.0, np.abs(ref)))


@pytest.mark.parametrize("confidence", [0.5, 0.9, 0.95, 0.99, 0.999, 1.0 - 1e-9])
def test_band_z_is_the_two_sided_quantile(confidence):
    z = band_z(confidence)
    assert z == pytest.approx(-float(ndtri(0.5 * (1.0 - confidence))), rel=1e-14)
    assert band_z(0.99) == pytest.approx(2.5758293035489, abs=1e-12)


def test_band_z_keeps_its_digits_next_to_one():
    """The largest double below 1: 0.5 + 0.5 c rounds to 1 there, the lower tail (1 - c) / 2 does not."""
    c = np.nextafter(1.0, 0.0)
    assert band_z(c) == pytest.approx(-float(ndtri(0.5 * (1.0 - c))), rel=1e-14)
    assert 8.0 < band_z(c) < 8.5


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_out_of_range_names_the_field_and_the_limit(bad):
    with pytest.raises(ValueError, match=r"confidence must be in \(0, 1\)"):
        band_z(bad)
    with pytest.raises(ValueError, match=r"probability in \(0, 1\)"):
        quantile(bad)
