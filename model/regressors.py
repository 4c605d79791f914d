"""NARX regressors, eq. (3): x_i = [y_{i-1}, ..., y_{i-ny}, u_i, u_{i-1}, ..., u_{i-nu+1}].

Regressors are built per record and stacked, so no lag window straddles two records. A gap (NaN samples in u
or y, ``model.gaps``) is a record break too: a row whose lag window holds a missing sample is left out.
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

    Row r is x_i for i = i0 + r, i0 = max(ny, nu - 1). A record with gaps (NaN in u or y, ``model.gaps``) is
    cut at them: a row is kept when no sample of u or y in [i - i0, i] is missing, so no lag window crosses a gap
    and the rows are those of the gap-free pieces, each stacked as a record of its own. Raises ValueError
    (naming the argument and the limit) for invalid lags, u/y that are not 1-D sequences of numbers of one
    length, or a record with no complete lag window.
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
    Y = y[i0:].copy()
    miss = np.isnan(u) | np.isnan(y)
    if miss.any():  # keep row i when no sample of u or y in [i - i0, i] is missing (the piece's own rows)
        c = np.concatenate([[0], np.cumsum(miss)])
        keep = c[i0 + 1: n + 1] - c[: n - i0] == 0
        if not keep.any():
            raise ValueError(f"record has no complete lag window outside its gaps (NaN samples): ny={ny}, nu={nu} "
                             f"need {i0 + 1} consecutive samples")
        X, Y = X[keep], Y[keep]
    return X, Y


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


# ---------------------------------------------------------------------------------------------------------------
# Several inputs and outputs: eq. (3) over every channel's lags
def _columns(name: str, v) -> np.ndarray:
    """``v`` as a (n, channels) float64 array (a 1-D sequence is one channel); ValueError naming ``name``."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an (n,) or (n, channels) array of numbers") from None
    if a.ndim == 1:
        return a[:, None]
    if a.ndim != 2 or a.shape[1] < 1:
        raise ValueError(f"{name} must be an (n,) or (n, channels) array of numbers, got shape {a.shape}")
    return a


def mimo_columns(n_outputs: int, n_inputs: int, ny: int, nu: int) -> list[tuple[str, int, int]]:
    """What each column of a ``mimo_regressors`` row is: ("y", output channel, lag j >= 1) for y_{i-j} or
    ("u", input channel, lag j >= 0) for u_{i-j}, in column order."""
    return ([("y", o, j) for o in range(n_outputs) for j in range(1, ny + 1)]
            + [("u", k, j) for k in range(n_inputs) for j in range(nu)])


def mimo_regressors(u, y, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (3) for several channels: X (n - i0, n_outputs ny + n_inputs nu) and targets Y (n - i0, n_outputs).

    u: (n,) or (n, n_inputs) [input units]; y: (n,) or (n, n_outputs) [output units]. Row r is the regressor
    of sample i = i0 + r, i0 = max(ny, nu - 1), shared by every output:
    [y_{i-1..i-ny} of output 0, ..., of output n_outputs - 1, u_{i..i-nu+1} of input 0, ..., of the last input]
    (``mimo_columns``). One input and one output give ``narx_regressors``'s X, and Y as one column. A row whose
    window holds a NaN (a gap) is left out, as ``narx_regressors`` does.
    """
    ny, nu = check_lags(ny, nu)
    U, Yc = _columns("u", u), _columns("y", y)
    if U.shape[0] != Yc.shape[0]:
        raise ValueError(f"u and y must have the same length, got {U.shape[0]} and {Yc.shape[0]} samples")
    i0 = first_index(ny, nu)
    n = U.shape[0]
    if n <= i0:
        raise ValueError(f"record has {n} samples; at least {i0 + 1} are needed for ny={ny}, nu={nu}")
    no, ni = Yc.shape[1], U.shape[1]
    rows = n - i0
    X = np.empty((rows, no * ny + ni * nu))
    for o in range(no):
        for j in range(1, ny + 1):
            X[:, o * ny + j - 1] = Yc[i0 - j: n - j, o]
    base = no * ny
    for k in range(ni):
        for j in range(nu):
            X[:, base + k * nu + j] = U[i0 - j: n - j, k]
    Y = Yc[i0:].copy()
    if np.isnan(U).any() or np.isnan(Yc).any():
        keep = ~(np.isnan(X).any(axis=1) | np.isnan(Y).any(axis=1))
        if not keep.any():
            raise ValueError(f"record has no complete lag window outside its gaps (NaN samples): ny={ny}, nu={nu} "
                             f"need {i0 + 1} consecutive samples")
        X, Y = X[keep], Y[keep]
    return X, Y


def stack_mimo_regressors(records, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X, Y (rows, n_outputs) and the record index of each row for many (u, y) records of the same channels,
    stacked (``mimo_regressors``); no window straddles two records. ValueError prefixed with ``record K:``."""
    ny, nu = check_lags(ny, nu)
    Xs, Ys, idx = [], [], []
    shape = None
    for k, rec in enumerate(records):
        try:
            u, y = rec
        except (TypeError, ValueError):
            raise ValueError(f"record {k}: expected a (u, y) pair") from None
        try:
            X, Y = mimo_regressors(u, y, ny, nu)
        except ValueError as exc:
            raise ValueError(f"record {k}: {exc}") from None
        if shape is not None and (X.shape[1], Y.shape[1]) != shape:
            raise ValueError(f"record {k}: its channels differ from record 0's (every record needs the same "
                             "inputs and outputs)")
        shape = (X.shape[1], Y.shape[1])
        Xs.append(X)
        Ys.append(Y)
        idx.append(np.full(Y.shape[0], k))
    if not Xs:
        raise ValueError("stack_mimo_regressors needs at least one record (u, y)")
    return np.vstack(Xs), np.vstack(Ys), np.concatenate(idx)
