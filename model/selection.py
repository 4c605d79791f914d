"""Training-point selection: caps the number of GP training points so ML-II stays tractable.

* ``stride``: evenly spaced rows over all records (keeps the time coverage).
* ``random``: a seeded uniform draw of rows.

Record weights (``weights``, one positive number per record, 1 each by default) set each record's share
of the rows for ``stride`` and ``random``: record k gets a share proportional to its rows times its
weight, so a weight of 4 gives a record four times the rows per second of a record of weight 1 (a short
broadband noise run next to many periodic sine windows, whose rows repeat every cycle).
* ``resonance``: section 4.2 of the paper: only rows from the region of largest response
  amplitude (the resonance of a sweep). Rows are ranked by a moving envelope of |y|; the top
  ``2 * cap`` rows per record are kept, then a seeded random draw takes ``cap`` of them.
"""
from __future__ import annotations

import numpy as np

SELECTIONS = ("stride", "random", "resonance")


def select_rows(Y: np.ndarray, record_index: np.ndarray, cap: int | None, method: str = "stride",
                seed: int = 0, envelope_window: int = 64, weights=None) -> np.ndarray:
    """Indices of at most ``cap`` rows of the stacked regressors (sorted).

    weights: None (every record alike) or one positive weight per record, indexed by ``record_index``'s
    values (``stride`` and ``random``; ``resonance`` ranks by the response envelope and takes none).
    """
    n = Y.size
    if method not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {method!r}")
    w = check_weights(weights, record_index)
    if w is not None and method == "resonance":
        raise ValueError("row weights apply to selection 'stride' or 'random', not 'resonance'")
    if cap is None or cap >= n:
        return np.arange(n)
    if cap < 1:
        raise ValueError(f"max_train_points must be at least 1, got {cap}")
    rng = np.random.default_rng(seed)
    if w is not None:
        return _weighted(record_index, cap, w, method, rng)
    if method == "stride":
        return np.unique(np.linspace(0, n - 1, cap).round().astype(int))
    if method == "random":
        return np.sort(rng.choice(n, cap, replace=False))
    # resonance: envelope ranking within each record, pooled
    from scipy.ndimage import maximum_filter1d  # here: only training's resonance selection needs scipy.ndimage

    env = np.empty(n)
    for k in np.unique(record_index):
        rows = np.flatnonzero(record_index == k)
        env[rows] = maximum_filter1d(np.abs(Y[rows]), size=envelope_window, mode="nearest")
    pool = np.argsort(env)[::-1][: min(n, 2 * cap)]
    return np.sort(rng.choice(pool, cap, replace=False))


def check_weights(weights, record_index: np.ndarray) -> np.ndarray | None:
    """``weights`` as a float array (one per record), or None when absent or all equal."""
    if weights is None:
        return None
    w = np.asarray(weights, dtype=float).ravel()
    n_rec = int(np.max(record_index)) + 1 if np.size(record_index) else 0
    if w.size != n_rec:
        raise ValueError(f"row weights: expected one per record ({n_rec}), got {w.size}")
    bad = np.flatnonzero(~(np.isfinite(w) & (w > 0)))
    if bad.size:
        raise ValueError(f"row weight of record {int(bad[0])} must be a positive number, got {w[bad[0]]!r}")
    return None if np.all(w == w[0]) else w


def _weighted(record_index: np.ndarray, cap: int, w: np.ndarray, method: str, rng) -> np.ndarray:
    """``cap`` rows shared among the records in proportion to rows x weight (largest remainders), each
    record's share by stride (evenly spaced in it) or a seeded draw."""
    counts = np.bincount(record_index, minlength=w.size)
    want = counts * w
    share = np.zeros(w.size)
    free = counts > 0
    left = float(min(cap, counts.sum()))
    while free.any():  # a record short of its share gives all its rows; the rest share what is left
        share[free] = left * want[free] / want[free].sum()
        full = free & (share >= counts)
        if not full.any():
            break
        share[full] = counts[full]
        left -= float(counts[full].sum())
        free &= ~full
    take = np.minimum(np.floor(share).astype(int), counts)
    for k in np.argsort(-(share - take)):  # largest remainders first, while rows remain
        if take.sum() >= min(cap, counts.sum()):
            break
        if take[k] < counts[k]:
            take[k] += 1
    out = []
    for k in np.flatnonzero(take):
        rows = np.flatnonzero(record_index == k)
        if method == "stride":
            out.append(rows[np.unique(np.linspace(0, rows.size - 1, take[k]).round().astype(int))])
        else:
            out.append(rng.choice(rows, take[k], replace=False))
    return np.sort(np.concatenate(out))
