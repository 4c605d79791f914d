"""Record row weights: a training record's share of the ML-II rows (model.selection, GPNARX.fit via
Record.meta["row_weight"], a dataset config's ``meta = { row_weight = ... }``)."""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.record import Record
from gpnarx.model.selection import select_rows


def _index(sizes):
    return np.concatenate([np.full(n, k) for k, n in enumerate(sizes)])


@pytest.mark.parametrize("method", ["stride", "random"])
def test_a_weight_sets_each_records_share_of_the_rows(method):
    idx = _index([9000, 1000])
    rows = select_rows(np.zeros(idx.size), idx, 1000, method, seed=0, weights=[1.0, 4.0])
    per = np.bincount(idx[rows], minlength=2)
    # shares proportional to rows x weight: 9000 : 4000
    assert rows.size == 1000 and per.tolist() == [692, 308]
    assert np.all(np.diff(rows) > 0)


def test_equal_weights_give_the_unweighted_rows():
    idx = _index([3000, 500, 1200])
    Y = np.zeros(idx.size)
    for method in ("stride", "random"):
        assert np.array_equal(select_rows(Y, idx, 700, method, 3, weights=[2.0, 2.0, 2.0]),
                              select_rows(Y, idx, 700, method, 3))


def test_a_record_never_gives_more_rows_than_it_has():
    idx = _index([5000, 100])
    rows = select_rows(np.zeros(idx.size), idx, 1000, "stride", weights=[1.0, 1000.0])
    per = np.bincount(idx[rows], minlength=2)
    assert per[1] == 100 and rows.size == 1000


@pytest.mark.parametrize("weights, msg", [([1.0], "one per record"), ([1.0, 0.0], "positive"),
                                          ([1.0, float("nan")], "positive")])
def test_bad_weights_are_refused(weights, msg):
    with pytest.raises(ValueError, match=msg):
        select_rows(np.zeros(20), _index([10, 10]), 5, "stride", weights=weights)


def test_resonance_selection_takes_no_weights():
    with pytest.raises(ValueError, match="resonance"):
        select_rows(np.zeros(20), _index([10, 10]), 5, "resonance", weights=[1.0, 2.0])


def test_fit_reads_the_weight_from_record_meta(sdof_data):
    u, y = sdof_data["u"], sdof_data["yn"]
    a = Record(u[:2000], y[:2000], 500.0, name="long")
    b = Record(u[2000:], y[2000:], 500.0, name="short", meta={"row_weight": 3.0})
    theta = None
    plain = GPNARX(ny=4, nu=4, max_train_points=300, n_restarts=0).fit([a, Record(b.u, b.y, 500.0)])
    theta = plain.theta_
    weighted = GPNARX(ny=4, nu=4, max_train_points=300, n_restarts=0).fit([a, b], theta=theta)
    # the short record's rows are the last ones of the stacked regressors
    X_plain, X_w = plain.posterior_.points, weighted.posterior_.points
    assert X_plain.shape == X_w.shape
    assert not np.allclose(X_plain, X_w)
    bad = Record(b.u, b.y, 500.0, name="bad", meta={"row_weight": -1})
    with pytest.raises(ValueError, match=r"records\[1\] \(bad\): row_weight must be a positive number"):
        GPNARX(ny=4, nu=4, max_train_points=300, n_restarts=0).fit([a, bad], theta=theta)
