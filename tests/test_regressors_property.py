"""Property tests (hypothesis) of the NARX regressor builder, eq. (3) (``model.regressors``).

For random lag orders ny, nu and record lengths, every row of ``narx_regressors`` is checked
against the lagged values read by direct indexing,

    x_i = [y_{i-1}, ..., y_{i-ny}, u_i, u_{i-1}, ..., u_{i-nu+1}],  target y_i,
    for i = max(ny, nu - 1), ..., n - 1,

``stack_regressors`` is checked to be the per-record blocks stacked (no window straddles two
records: each row equals the row built from its own record alone), and bad arguments (records too
short for the lags, invalid lags, mismatched or non-1-D arrays, no records) raise a ValueError
whose message names the problem, never an IndexError or a numpy broadcasting error.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpnarx.model.regressors import (
    MAX_LAGS,
    check_lags,
    first_index,
    narx_regressors,
    stack_regressors,
)

SETTINGS = settings(max_examples=50, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])

lags = st.integers(1, 12)


def _record(draw, n):
    # distinct values per sample (position encoded) so a shifted index cannot pass by accident
    noise = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(noise)
    u = np.arange(n) + rng.uniform(0.0, 0.5, n)
    y = -1000.0 - np.arange(n) - rng.uniform(0.0, 0.5, n)
    return u, y


@st.composite
def lagged_record(draw):
    ny, nu = draw(lags), draw(lags)
    i0 = max(ny, nu - 1)
    n = draw(st.integers(i0 + 1, i0 + 40))
    u, y = _record(draw, n)
    return ny, nu, u, y


def _expected_row(u, y, i, ny, nu):
    return [y[i - j] for j in range(1, ny + 1)] + [u[i - j] for j in range(nu)]


@SETTINGS
@given(lagged_record())
def test_rows_are_the_lagged_values(case):
    ny, nu, u, y = case
    X, Y = narx_regressors(u, y, ny, nu)
    i0 = max(ny, nu - 1)
    assert first_index(ny, nu) == i0
    n = u.size
    assert X.shape == (n - i0, ny + nu) and Y.shape == (n - i0,)
    assert X.dtype == np.float64 and Y.dtype == np.float64
    for r, i in enumerate(range(i0, n)):
        assert X[r].tolist() == _expected_row(u, y, i, ny, nu), (ny, nu, i)
        assert Y[r] == y[i]
    # the target is never among its own regressors (y_i is not lagged into x_i)
    assert not np.any(X[:, :ny] == Y[:, None])
    # the result does not alias the inputs
    Y[:] = 0.0
    assert y[i0] != 0.0


@SETTINGS
@given(st.data())
def test_stack_never_straddles_records(data):
    ny, nu = data.draw(lags), data.draw(lags)
    i0 = max(ny, nu - 1)
    lengths = data.draw(st.lists(st.integers(i0 + 1, i0 + 25), min_size=1, max_size=4))
    records = []
    for k, n in enumerate(lengths):
        u, y = _record(data.draw, n)
        records.append((u + 1e4 * k, y - 1e4 * k))  # records differ in magnitude
    X, Y, idx = stack_regressors(records, ny, nu)
    assert X.shape == (sum(n - i0 for n in lengths), ny + nu) and Y.shape == idx.shape == (X.shape[0],)
    assert np.array_equal(np.bincount(idx, minlength=len(lengths)), [n - i0 for n in lengths])
    assert np.all(np.diff(idx) >= 0)
    for k, (u, y) in enumerate(records):
        Xk, Yk = narx_regressors(u, y, ny, nu)
        assert np.array_equal(X[idx == k], Xk) and np.array_equal(Y[idx == k], Yk)
        # every value in record k's rows comes from record k
        own = np.concatenate([u, y])
        assert np.isin(X[idx == k], own).all()


@SETTINGS
@given(st.data())
def test_lists_are_accepted_like_arrays(data):
    ny, nu = data.draw(lags), data.draw(lags)
    n = data.draw(st.integers(max(ny, nu - 1) + 1, max(ny, nu - 1) + 10))
    u, y = _record(data.draw, n)
    X1, Y1 = narx_regressors(u, y, ny, nu)
    X2, Y2 = narx_regressors(u.tolist(), y.tolist(), ny, nu)
    assert np.array_equal(X1, X2) and np.array_equal(Y1, Y2)


@SETTINGS
@given(st.data())
def test_too_short_records_raise_a_clear_error(data):
    ny, nu = data.draw(lags), data.draw(lags)
    i0 = max(ny, nu - 1)
    n = data.draw(st.integers(0, i0))
    u, y = _record(data.draw, n)
    with pytest.raises(ValueError, match=rf"{n} samples.*at least {i0 + 1}.*ny={ny}, nu={nu}"):
        narx_regressors(u, y, ny, nu)
    # in a stack, the error names which record is too short
    good = _record(data.draw, i0 + 5)
    pos = data.draw(st.integers(0, 2))
    records = [good] * pos + [(u, y)] + [good]
    with pytest.raises(ValueError, match=rf"record {pos}\b.*{n} samples.*at least {i0 + 1}"):
        stack_regressors(records, ny, nu)


bad_lag = st.one_of(st.integers(-50, 0), st.integers(MAX_LAGS + 1, 10**6), st.floats(allow_nan=True),
                    st.booleans(), st.none(), st.text(max_size=3))


@SETTINGS
@given(bad=bad_lag, which=st.sampled_from(["ny", "nu"]), other=lags)
def test_invalid_lags_raise_a_clear_error(bad, which, other):
    kw = {"ny": other, "nu": other, which: bad}
    u, y = np.arange(300.0), np.arange(300.0)
    with pytest.raises(ValueError, match=rf"^{which} must be"):
        check_lags(kw["ny"], kw["nu"])
    with pytest.raises(ValueError, match=rf"^{which} must be"):
        narx_regressors(u, y, kw["ny"], kw["nu"])
    with pytest.raises(ValueError, match=rf"^{which} must be"):
        stack_regressors([(u, y)], kw["ny"], kw["nu"])


@SETTINGS
@given(st.data())
def test_malformed_records_raise_a_clear_error(data):
    ny, nu = data.draw(lags), data.draw(lags)
    i0 = max(ny, nu - 1)
    n = data.draw(st.integers(i0 + 1, i0 + 20))
    u, y = _record(data.draw, n)
    k = data.draw(st.integers(1, 5))
    with pytest.raises(ValueError, match=r"same length"):
        narx_regressors(u, np.concatenate([y, y[:k]]), ny, nu)
    with pytest.raises(ValueError, match=r"same length"):
        narx_regressors(u[:-1] if n > 1 else u[:0], y, ny, nu)
    with pytest.raises(ValueError, match=r"\bu\b.*1-D"):
        narx_regressors(np.stack([u, u], axis=1), y, ny, nu)
    with pytest.raises(ValueError, match=r"\by\b.*1-D"):
        narx_regressors(u, y[:, None], ny, nu)
    with pytest.raises(ValueError, match=r"\bu\b.*numbers"):
        narx_regressors(["a"] * n, y, ny, nu)
    with pytest.raises(ValueError, match=r"record 1\b.*same length"):
        stack_regressors([(u, y), (u, y[:-1])], ny, nu)
    with pytest.raises(ValueError, match=r"record 0\b.*\(u, y\) pair"):
        stack_regressors([(u,)], ny, nu)


def test_no_records_is_a_clear_error():
    with pytest.raises(ValueError, match="at least one record"):
        stack_regressors([], 2, 2)
