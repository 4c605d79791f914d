"""Standard normal quantiles: the z of a two-sided band and of one tail.

From the standard library's ``statistics.NormalDist`` (Wichura's algorithm AS241, full double precision;
scipy.special.ndtri gives the same numbers to 1e-15). Importing scipy.special instead costs a one-shot
command such as ``gpnarx predict`` about a tenth of a second.
"""
from __future__ import annotations

from statistics import NormalDist

_STANDARD = NormalDist()


def quantile(p: float) -> float:
    """z with P(Z <= z) = p for a standard normal Z; 0 < p < 1."""
    p = float(p)
    if not 0.0 < p < 1.0:
        raise ValueError(f"a normal quantile needs a probability in (0, 1), got {p}")
    return _STANDARD.inv_cdf(p)


def band_z(confidence: float) -> float:
    """z of a two-sided band at ``confidence`` (0 < confidence < 1): P(|Z| <= z) = confidence."""
    c = float(confidence)
    if not 0.0 < c < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    # from the lower tail (1 - c) / 2, which keeps its digits where 0.5 + 0.5 c would round to 1
    return -_STANDARD.inv_cdf(0.5 * (1.0 - c))
