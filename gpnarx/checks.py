"""Checks of values that every layer makes, written once."""
from __future__ import annotations

from numbers import Integral


def is_int(v, lo: int | None = None, hi: int | None = None) -> bool:
    """Whether ``v`` is an integer (a Python or numpy integer, not a bool) in [``lo``, ``hi``] (None: no bound).
    The caller raises its own error naming the value."""
    if isinstance(v, bool) or not isinstance(v, Integral):
        return False
    return (lo is None or v >= lo) and (hi is None or v <= hi)
