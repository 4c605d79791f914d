"""``gpnarx train`` with a training record that holds a gap (``model.gaps``): the record file's NaN samples are a
record break, no lag window crosses them; every other role must be gap-free."""
from __future__ import annotations

import json

import numpy as np
from conftest import sdof_simulate

from gpnarx.cli.main import main
from gpnarx.model.regressors import stack_regressors
from gpnarx.storage.bundle import load_bundle

FS = 500.0
CONFIG = """
name = "gappy"
[system]
fs = 500.0
output = "displacement"
[model]
ny = 4
nu = 4
max_train_points = 100000
restarts = 0
mode = "exact"
[predict]
mc_paths = 16
method = "linear"
[[records]]
name = "train"
roles = {roles}
path = "{train}"
[[records]]
name = "check"
roles = ["verify"]
path = "{check}"
"""


def _records(tmp_path):
    rng = np.random.default_rng(3)
    u = rng.normal(size=900)
    y = sdof_simulate(u) * 1e3
    y = y + 0.02 * np.std(y) * rng.normal(size=y.size)
    ug = u[:600].copy()
    ug[250:280] = np.nan  # a 60 ms dropout
    np.savez(tmp_path / "train.npz", u=ug, y=y[:600], fs=FS)
    np.savez(tmp_path / "check.npz", u=u[600:], y=y[600:], fs=FS)
    return u, y


def test_train_with_a_gap_in_a_training_record(tmp_path, capsys):
    u, y = _records(tmp_path)
    cfg = tmp_path / "gappy.toml"
    cfg.write_text(CONFIG.format(roles='["train"]', train=tmp_path / "train.npz", check=tmp_path / "check.npz"))
    reg = tmp_path / "reg"
    assert main(["--json", "train", str(cfg), "--registry", str(reg), "--no-report"]) == 0
    out = json.loads(capsys.readouterr().out)
    b = load_bundle(reg / "gappy" / out["version"])
    # the regressor rows are the two pieces' (no window crosses the gap): 246 + 316 rows for ny = nu = 4
    _, Y, _ = stack_regressors([(u[:250], y[:250]), (u[280:600], y[280:600])], 4, 4)
    assert b.manifest["training"]["n_rows"] == Y.size == 246 + 316
    assert b.model.n_train_ == Y.size and np.all(np.isfinite(b.model.posterior_.alpha))
    # the same posterior as the two pieces given as two records, with the bundle's hyperparameters
    from gpnarx.model.estimator import GPNARX

    two = GPNARX(ny=4, nu=4, max_train_points=100000, n_restarts=0, mode="exact").fit(
        [(u[:250], y[:250]), (u[280:600], y[280:600])], theta=b.model.theta_)
    np.testing.assert_allclose(b.model.posterior_.alpha, two.posterior_.alpha, rtol=1e-9, atol=0)
    assert np.isfinite(b.manifest["training"]["records"]["check"]["fit"])


def test_a_gap_in_a_scored_record_is_refused(tmp_path, capsys):
    _records(tmp_path)
    cfg = tmp_path / "gappy.toml"
    cfg.write_text(CONFIG.format(roles='["train", "verify"]', train=tmp_path / "train.npz",
                                 check=tmp_path / "check.npz"))
    assert main(["train", str(cfg), "--registry", str(tmp_path / "reg"), "--no-report"]) == 1
    err = capsys.readouterr().err
    assert "NaN" in err and "train" in err
