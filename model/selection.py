"""Training-point selection: caps the number of GP training points so ML-II stays tractable.

* ``stride``: evenly spaced rows over all records (keeps the time coverage).
* ``random``: a seeded uniform draw of rows.
* ``resonance``: section 4.2 of the paper: only rows from the region of largest response
  amplitude (the resonance of a sweep). Rows are ranked by a moving envelope of |y|; the top
  ``2 * cap`` rows per record are kept, then a seeded random draw takes ``cap`` of them.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d

SELECTIONS = ("stride", "random", "resonance")


def select_rows(Y: np.ndarray, record_index: np.ndarray, cap: int | None, method: str = "stride",
                seed: int = 0, envelope_window: int = 64) -> np.ndarray:
    """Indices of at most ``cap`` rows of the stacked regressors (sorted)."""
    n = Y.size
    if method not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {method!r}")
    if cap is None or cap >= n:
        return np.arange(n)
    if cap < 1:
        raise ValueError(f"max_train_points must be at least 1, got {cap}")
    rng = np.random.default_rng(seed)
    if method == "stride":
        return np.unique(np.linspace(0, n - 1, cap).round().astype(int))
    if method == "random":
        return np.sort(rng.choice(n, cap, replace=False))
    # resonance: envelope ranking within each record, pooled
    env = np.empty(n)
    for k in np.unique(record_index):
        rows = np.flatnonzero(record_index == k)
        env[rows] = maximum_filter1d(np.abs(Y[rows]), size=envelope_window, mode="nearest")
    pool = np.argsort(env)[::-1][: min(n, 2 * cap)]
    return np.sort(rng.choice(pool, cap, replace=False))
