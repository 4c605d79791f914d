"""Records with gaps: runs of missing samples (NaN) in the input u or the output y.

Acquisition drops samples; a monitoring system sends what it has and marks the rest as NaN (``null`` in a JSON
array). A gap is a record break:

* in training (``regressors.narx_regressors``), no lag window crosses it: a regressor row whose window
  [y_{i-ny} .. y_i, u_{i-nu+1} .. u_i] holds a missing sample is left out, which is the same as cutting the record
  at its gaps and stacking the pieces as records of their own;
* in prediction (``GPNARX.simulate``), the answer holds NaN through the gap, and after it the free run restarts
  as at a record's start: from the measured outputs (the piece's first ny samples) where y is given, from rest
  otherwise; input lags from before the piece are zeros (rest), as at a record's start. Fit and coverage skip
  the gaps (``metrics``).

Limits (``check_gaps``): a gap may be at most ``MAX_GAP_SECONDS`` long, and at most ``MAX_GAP_SHARE`` of a
record may be missing. A longer gap means two acquisitions, better sent as two records; a record mostly missing
tells a fit or a band little. Both are refusals naming the field (``u`` or ``y``) and the limit.
"""
from __future__ import annotations

import numpy as np

#: the longest gap a record may hold [s]: a dropout, not a break between two acquisitions (send those as
#: two records). At the rig's 1024 Hz: 2048 samples; several times the rig's free decay (about 0.3 s).
MAX_GAP_SECONDS = 2.0
#: the largest share of a record's samples that may be missing (dimensionless)
MAX_GAP_SHARE = 0.5


class GapError(ValueError):
    """A record whose gaps pass a limit: ``field`` (``u`` or ``y``: where the offending gap's first sample is
    missing) and ``limit`` (``MAX_GAP_SECONDS`` [s] or ``MAX_GAP_SHARE``)."""

    def __init__(self, detail: str, field: str, limit: float):
        super().__init__(detail)
        self.field = field
        self.limit = limit


def missing(u, y=None) -> np.ndarray:
    """Boolean mask of the samples missing (NaN) in u or, when given, y."""
    miss = np.isnan(np.asarray(u, dtype=float))
    if y is not None:
        miss = miss | np.isnan(np.asarray(y, dtype=float))
    return miss


def find_gaps(u, y=None) -> list[tuple[int, int]]:
    """The gaps of a record: (start, end) sample indices of each run of missing samples (end exclusive), in
    order; [] for a record without one."""
    miss = missing(u, y)
    if not miss.any():
        return []
    d = np.diff(np.concatenate([[0], miss.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def pieces(n: int, gaps: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The gap-free pieces (start, end) of a record of n samples with ``gaps`` (end exclusive)."""
    out, at = [], 0
    for a, b in gaps:
        if a > at:
            out.append((at, a))
        at = b
    if at < n:
        out.append((at, n))
    return out


def gap_list(gaps: list[tuple[int, int]], fs: float) -> list[dict]:
    """The gaps as an answer lists them: ``start``, ``end`` (samples, end exclusive) and ``start_s``, ``end_s``
    [s] (fs in Hz)."""
    return [{"start": a, "end": b, "start_s": a / fs, "end_s": b / fs} for a, b in gaps]


def check_gaps(u, y, fs: float, max_gap_seconds: float = MAX_GAP_SECONDS,
               max_share: float = MAX_GAP_SHARE) -> list[tuple[int, int]]:
    """The record's gaps (``find_gaps``) when they are within the limits; a ``GapError`` naming the field
    (``u`` or ``y``) and the limit otherwise. fs [Hz]."""
    gaps = find_gaps(u, y)
    if not gaps:
        return gaps
    n = np.asarray(u).size
    uu = np.asarray(u, dtype=float)

    def field_of(a: int) -> str:
        return "u" if np.isnan(uu[a]) else "y"

    longest = max(gaps, key=lambda g: g[1] - g[0])
    if (longest[1] - longest[0]) / fs > max_gap_seconds:
        a, b = longest
        raise GapError(f"{field_of(a)} has a gap of {b - a} samples ({(b - a) / fs:.3g} s, samples {a} to {b - 1}); "
                       f"the limit is {max_gap_seconds:g} s: send the parts before and after it as two records",
                       field_of(a), max_gap_seconds)
    lost = sum(b - a for a, b in gaps)
    if lost > max_share * n:
        f = field_of(gaps[0][0])
        raise GapError(f"{f}: {lost} of {n} samples are missing ({100 * lost / n:.0f} %); at most "
                       f"{100 * max_share:g} % of a record may be gaps", f, max_share)
    return gaps
