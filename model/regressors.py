"""NARX regressors, eq. (3): x_i = [y_{i-1}, ..., y_{i-ny}, u_i, u_{i-1}, ..., u_{i-nu+1}].

Regressors are built per record and stacked, so no lag window straddles two records.
"""
from __future__ import annotations

import numpy as np

from gpnarx.checks import is_int

MAX_LAGS = 200  # upper limit on ny and nu (each)


def check_lags(ny, nu) -> tuple[int, int]:
    """Validate lag orders: ny in [1, MAX_LAGS], nu in [1, MAX_LAGS]."""
    for name, val in (("ny", ny), ("nu", nu)):
        if not is_int(val):
            raise ValueError(f"{name} must be an integer between 1 and {MAX_LAGS}, got {val!r}")
        if not 1 <= int(val) <= MAX_LAGS:
            raise ValueError(f"{name} must be between 1 and {MAX_LAGS}, got {val}")
    return int(ny), int(nu)


def first_index(ny: int, nu: int) -> int:
    """First sample index with a complete lag window: max(ny, nu - 1)."""
    return max(ny, nu - 1)


def _series(name: str, v) -> np.ndarray:
    """``v`` as a 1-D float64 array; ValueError naming ``name`` otherwise."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 1-D sequence of numbers") from None
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D sequence of numbers, got an array of shape {a.shape}")
    return a


def narx_regressors(u: np.ndarray, y: np.ndarray, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """Regression matrix X (n - i0, ny + nu) and targets Y (n - i0,) for one record, eq. (3).

    Row r is x_i for i = i0 + r, i0 = max(ny, nu - 1). Raises ValueError (naming the argument and the
    limit) for invalid lags, u/y that are not 1-D sequences of numbers of one length, or a record
    with no complete lag window.
    """
    ny, nu = check_lags(ny, nu)
    u, y = _series("u", u), _series("y", y)
    if u.size != y.size:
        raise ValueError(f"u and y must have the same length, got {u.size} and {y.size} samples")
    i0 = first_index(ny, nu)
    n = u.size
    if n <= i0:
        raise ValueError(
            f"record has {n} samples; at least {i0 + 1} are needed for ny={ny}, nu={nu}"
        )
    rows = n - i0
    X = np.empty((rows, ny + nu))
    for j in range(1, ny + 1):  # y_{i-j}
        X[:, j - 1] = y[i0 - j : n - j]
    for j in range(nu):  # u_{i-j}
        X[:, ny + j] = u[i0 - j : n - j]
    return X, y[i0:].copy()


def stack_regressors(records, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X, Y and the record index of each row, for many records (u, y) stacked; no window straddles two.

    A record that is not a (u, y) pair or fails ``narx_regressors`` raises ValueError prefixed with
    ``record K:`` (its position).
    """
    ny, nu = check_lags(ny, nu)
    Xs, Ys, idx = [], [], []
    for k, rec in enumerate(records):
        try:
            u, y = rec
        except (TypeError, ValueError):
            raise ValueError(f"record {k}: expected a (u, y) pair") from None
        try:
            X, Y = narx_regressors(u, y, ny, nu)
        except ValueError as exc:
            raise ValueError(f"record {k}: {exc}") from None
        Xs.append(X)
        Ys.append(Y)
        idx.append(np.full(Y.size, k))
    if not Xs:
        raise ValueError("stack_regressors needs at least one record (u, y)")
    return np.vstack(Xs), np.concatenate(Ys), np.concatenate(idx)
