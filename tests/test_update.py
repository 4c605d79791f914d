"""Updates from new healthy records (issue 53): ``GPNARX.partial_fit``, ``training.update`` and ``gpnarx update``.

Tolerances are absolute in standardised units (the posterior's outputs: mean of eq. 8 and latent variance of eq. 9
at standardised regressors), where the output has unit variance.
"""
from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from gpnarx.cli.main import main
from gpnarx.model.estimator import GPNARX
from gpnarx.model.gp import ExactPosterior
from gpnarx.model.gp_update import append_rows, keep_rows, targets
from gpnarx.model.record import Record
from gpnarx.model.regressors import stack_regressors
from gpnarx.storage.bundle import load_bundle, save_bundle
from gpnarx.storage.registry import Registry

FS = 100.0
TOL = 1e-8  # absolute, standardised units


def system(u, a=(1.5, -0.7), gain=0.3, cubic=0.2):
    """A mildly nonlinear second-order system: y[t] = a1 y[t-1] + a2 y[t-2] + g u[t-1] - c y[t-1]^3."""
    y = np.zeros_like(u)
    for t in range(2, u.size):
        y[t] = a[0] * y[t - 1] + a[1] * y[t - 2] + gain * u[t - 1] - cubic * y[t - 1] ** 3
    return y


def record(seed, n=400, name=None, **kw):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    y = system(u, **kw) + 0.01 * rng.normal(size=n)
    return Record(u, y, FS, name=name or f"r{seed}")


def theta(bias):
    """Fixed hyperparameters (no ML-II): Matern 3/2 + cubic with constant term 0.1 bias^3, noise 1e-3."""
    return np.log([0.5, 2.0, 0.1, 1.0, bias, 1e-3])


def fitted(bias=1.0, max_train_points=None, n=300):
    m = GPNARX(ny=2, nu=2, max_train_points=max_train_points, n_restarts=0)
    return m.fit([record(0, n)], theta=theta(bias))


def refit(model, X, y):
    """The exact posterior on rows X, targets y with the model's hyperparameters, as ``fit`` builds it."""
    return ExactPosterior.fit(model.kernel_, model.noise_var_, X, y, var_kernel=model._posterior_kernel())


def rows_of(model, rec):
    X, Y, _ = stack_regressors([(rec.u, rec.y)], model.ny, model.nu)
    return model.x_scaler_.transform(X), (Y - model.y_scaler_.mean_[0]) / model.y_scaler_.scale_[0]


def max_diffs(p, q, Xs):
    (m1, v1), (m2, v2) = p.predict(Xs), q.predict(Xs)
    return float(np.max(np.abs(m1 - m2))), float(np.max(np.abs(v1 - v2)))


# ------------------------------------------------------------------------------------------ the rank update
@pytest.mark.parametrize("bias", [1.0, 3.0])  # constant term 0.1 (no cap) and 2.7 (capped at 1: Sherman-Morrison)
def test_updated_posterior_equals_a_refit_on_the_same_rows(bias):
    m = fitted(bias)
    assert (m.posterior_.kernel.cap_shift() > 0) == (bias > 1)
    X0, y0 = rows_of(m, record(0, 300))
    new = record(1, 200)
    m.partial_fit([new])
    assert m.update_["rows_dropped"] == 0 and m.update_["factor"] == "rank update"
    X1, y1 = rows_of(m, new)
    assert m.update_["rows_added"] == X1.shape[0] == m.n_train_ - X0.shape[0]
    ref = refit(m, np.vstack([X0, X1]), np.concatenate([y0, y1]))
    np.testing.assert_array_equal(m.posterior_.X_train, ref.X_train)
    Xs, _ = rows_of(m, record(2, 300))  # unseen regressors
    dm, dv = max_diffs(m.posterior_, ref, Xs)
    assert dm < TOL and dv < TOL, (dm, dv)
    # and the one-step prediction (output units) through the estimator
    other = fitted(bias)
    other.posterior_ = ref
    a, b = m.predict_one_step([record(2, 300)]), other.predict_one_step([record(2, 300)])
    scale = m.y_scaler_.scale_[0]
    assert np.max(np.abs(a[0] - b[0])) / scale < TOL and np.max(np.abs(a[1] - b[1])) / scale < TOL


def test_the_factor_is_updated_not_refactored(monkeypatch):
    """The append keeps the old factor's block as it is and never calls a full factorisation."""
    import gpnarx.model.gp_update as U

    m = fitted(3.0)
    old = m.posterior_.Linv.copy()
    monkeypatch.setattr(U, "refactor", lambda *a, **k: pytest.fail("refactor called on an append"))
    m.partial_fit([record(1, 100)])
    n = old.shape[0]
    np.testing.assert_array_equal(m.posterior_.Linv[:n, :n], old)
    assert np.all(m.posterior_.Linv[:n, n:] == 0.0)


def test_update_of_a_loaded_bundle_recovers_the_targets(tmp_path):
    """A bundle stores no targets: they are recovered from alpha, and the update matches the in-memory one."""
    m = fitted(3.0)
    path = save_bundle(m, tmp_path, "toy", fs=FS, units={"u": "N", "y": "m"}, training={"n_rows": m.n_rows_})
    loaded = load_bundle(path).model
    _, y0 = rows_of(m, record(0, 300))
    assert np.max(np.abs(targets(loaded.posterior_) - y0)) < TOL
    assert loaded.n_rows_ == m.n_rows_
    new = record(1, 200)
    m.partial_fit([new])
    loaded.partial_fit([new])
    Xs, _ = rows_of(m, record(2, 300))
    dm, dv = max_diffs(m.posterior_, loaded.posterior_, Xs)
    assert dm < TOL and dv < TOL, (dm, dv)


def test_row_budget_keeps_the_selection_rule_and_refactors_the_kept_rows():
    m = fitted(3.0, max_train_points=150)
    old_rows = m.posterior_.X_train.copy()
    m.partial_fit([record(1, 400)])
    up = m.update_
    assert m.n_train_ == 150 and up["rows_added"] + (150 - up["rows_dropped"]) == 150
    assert up["rows_dropped"] > 0 and up["rule"] == "selection:stride"
    # stride: the kept old rows are spread over all of them, first and last included, in their order
    kept = m.posterior_.X_train[: 150 - up["rows_added"]]
    idx = [int(np.flatnonzero(np.all(old_rows == r, axis=1))[0]) for r in kept]
    assert idx == sorted(idx) and idx[0] == 0 and idx[-1] >= 140
    ref = refit(m, m.posterior_.X_train, targets(m.posterior_))
    Xs, _ = rows_of(m, record(2, 300))
    dm, dv = max_diffs(m.posterior_, ref, Xs)
    assert dm < TOL and dv < TOL


def test_keep_rows_and_append_check_their_arguments():
    p = fitted().posterior_
    with pytest.raises(ValueError, match="rows must be distinct indices"):
        keep_rows(p, [0, 0])
    with pytest.raises(ValueError, match="X_new must have shape"):
        append_rows(p, np.zeros((3, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="y_new has 2 values for 3 rows"):
        append_rows(p, np.zeros((3, 4)), np.zeros(2))


def test_partial_fit_refusals():
    m = fitted()
    with pytest.raises(ValueError, match="rows must be an integer >= 1"):
        m.partial_fit([record(1, 100)], rows=0)
    with pytest.raises(ValueError, match=r"records\[0\] has 3 samples; ny=2, nu=2 need at least 4"):
        m.partial_fit([(np.zeros(3), np.zeros(3))])
    with pytest.raises(RuntimeError, match="not fitted"):
        GPNARX().partial_fit([record(1)])
    sparse = GPNARX(ny=2, nu=2, mode="sparse", n_inducing=16, max_train_points=100).fit([record(0, 200)],
                                                                                       theta=theta(1.0))
    with pytest.raises(ValueError, match="needs a retrain"):
        sparse.partial_fit([record(1, 100)])


def test_envelope_grows_with_the_new_records():
    m = fitted()
    before = dict(m.envelope_)
    big = record(1, 200)
    big = Record(2 * big.u, system(2 * big.u, cubic=0.0), FS, name="big")
    m.partial_fit([big])
    assert m.envelope_["u_peak"] == pytest.approx(float(np.max(np.abs(big.u))))
    assert m.envelope_["u_peak"] > before["u_peak"] and m.envelope_["n_records"] == before["n_records"] + 1


def test_recalibrate_noise_is_fits_rule_on_the_present_rows():
    m = GPNARX(ny=2, nu=2, max_train_points=None, n_restarts=0)
    held = [record(5, 300), record(6, 300)]
    m.fit([record(0, 300)], theta=theta(1.0), heldout=held)
    ref = GPNARX(ny=2, nu=2, max_train_points=None, n_restarts=0).fit([record(0, 300)], theta=theta(1.0))
    ref.recalibrate_noise(held)  # the same calibration through the update path: the same noise
    assert ref.noise_var_ == pytest.approx(m.noise_var_, rel=1e-9)
    assert ref.noise_calibration_["noise_var"] == pytest.approx(m.noise_calibration_["noise_var"], rel=1e-9)


# ------------------------------------------------------------------------------------------ training.update
def write_npz(path: Path, rec: Record) -> Path:
    np.savez(path, u=rec.u, y=rec.y, fs=rec.fs)
    return path


@pytest.fixture()
def monitored(tmp_path):
    """A toy model with a novelty monitor calibrated on three healthy records (``gpnarx calibrate``'s function)."""
    from gpnarx.training.novelty_calibration import calibrate

    m = GPNARX(ny=2, nu=2, max_train_points=None, n_restarts=0).fit([record(0, 400)], theta=theta(1.0))
    reg = tmp_path / "reg"
    save_bundle(m, reg, "toy", fs=FS, units={"u": "N", "y": "m"}, training={"n_rows": m.n_rows_},
                extra={"predict": {"method": "linear", "mc_paths": 64}})
    healthy = [record(10 + k, 400, name=f"h{k}") for k in range(3)]
    calibrate(load_bundle(reg / "toy" / "1"), healthy, reg, propagation="linear", n_paths=64)
    return reg, load_bundle(reg / "toy" / "2")


def damaged(n=400):
    """Same drive, a softer and less damped structure: the monitor's score is far above its threshold."""
    rng = np.random.default_rng(21)
    u = rng.normal(size=n)
    return Record(u, system(u, a=(1.7, -0.8), gain=0.25) + 0.01 * rng.normal(size=n), FS, name="damaged")


def test_a_novel_record_is_refused_and_accept_novel_says_so(monitored):
    from gpnarx.training.update import NovelRecordError, record_sha256, update

    reg, bundle = monitored
    bad = damaged()
    with pytest.raises(NovelRecordError,
                       match=r"damaged: the novelty monitor of toy:2 judges it novel .*--accept-novel"):
        update(bundle, [bad], reg)
    assert sorted(p.name for p in (reg / "toy").iterdir() if not p.name.startswith(".")) == ["1", "2"]
    when = dt.datetime(2030, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc)
    res = update(bundle, [bad], reg, accept_novel=True, now=when)
    man = json.loads((Path(res["path"]) / "manifest.json").read_text())
    lin = man["lineage"]
    assert res["version"] == "3" and lin["parent"]["version"] == "2" and lin["accept_novel"] is True
    assert lin["updated"] == "2030-01-02T03:04:05+00:00"
    (r,) = lin["records"]
    assert r["verdict"] == "novel" and r["score"] > r["threshold"] and r["sha256"] == record_sha256(bad.u, bad.y)
    assert lin["ancestors"] == ["2"] and lin["rows"]["rows_added"] > 0
    assert man["n_train"] == bundle.model.n_train_ + lin["rows"]["rows_added"]
    # the novelty block is kept (no config with healthy records to recalibrate it on) and the lineage says so
    assert man["novelty"]["threshold"] == bundle.manifest["novelty"]["threshold"]
    assert lin["recalibrated"]["novelty"].startswith("kept")


def test_a_healthy_record_updates_and_the_new_version_serves(monitored):
    from gpnarx.training.update import update

    reg, bundle = monitored
    good = record(30, 400, name="good")
    res = update(bundle, [good], reg)
    lin = res["lineage"]
    assert lin["records"][0]["verdict"] == "healthy" and lin["accept_novel"] is False
    new = load_bundle(res["path"])
    assert new.model.n_train_ == bundle.model.n_train_ + lin["rows"]["rows_added"]
    # the parent answers exactly as before; the registry's latest is the update
    before = bundle.model.predict_one_step([good])[0]
    np.testing.assert_array_equal(load_bundle(reg / "toy" / "2").model.predict_one_step([good])[0], before)
    assert Registry(reg).scan().get("toy").version == "3"


def test_the_service_picks_up_the_updated_version(monitored):
    import asyncio

    from fastapi.testclient import TestClient

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings
    from gpnarx.training.update import update

    reg, bundle = monitored
    app = create_app(reg, Settings(workers=1, queue_size=2, registry_poll=0))
    with TestClient(app) as c:
        assert c.get("/v1/models/toy").json()["version"] == "2"
        update(bundle, [record(30, 400, name="good")], reg)
        asyncio.run(app.state.service.reload(poll=True))
        info = c.get("/v1/models/toy").json()
        assert info["version"] == "3" and info["versions"] == ["1", "2", "3"]
        assert info["n_train"] > bundle.model.n_train_
        body = {"u": record(31, 200).u.tolist(), "fs": FS, "mc_paths": 8, "seed": 0}
        assert c.post("/v1/models/toy/versions/3/predict", json=body).status_code == 200


def test_update_needs_the_config_when_the_bundle_has_calibrations(tmp_path):
    from gpnarx.training.update import UpdateError, update

    m = GPNARX(ny=2, nu=2, max_train_points=None, n_restarts=0)
    m.fit([record(0, 300)], theta=theta(1.0), heldout=[record(5, 300)])
    path = save_bundle(m, tmp_path, "cal", fs=FS, units={}, training={"n_rows": m.n_rows_})
    with pytest.raises(UpdateError, match="config: model cal:1 has a noise calibration .* give the config"):
        update(load_bundle(path), [record(1, 200)], tmp_path)
    with pytest.raises(UpdateError, match="fs 50 Hz does not match model cal:1 fs 100 Hz"):
        update(load_bundle(path), [Record(np.zeros(100), np.zeros(100), 50.0, name="slow")], tmp_path)
    with pytest.raises(UpdateError, match="an update record needs its measured output y"):
        update(load_bundle(path), [Record(np.zeros(100), None, FS, name="r")], tmp_path)


# ------------------------------------------------------------------------------------------ the command line
def test_cli_update_json_and_errors(monitored, tmp_path, capsys):
    reg, _ = monitored
    good = write_npz(tmp_path / "good.npz", record(30, 400))
    bad = write_npz(tmp_path / "bad.npz", damaged())
    assert main(["update", "toy", str(bad), "--registry", str(reg)]) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]  # progress lines, then the error in one line
    assert "bad.npz: the novelty monitor of toy:2 judges it novel" in last and "--accept-novel" in last
    assert main(["update", "toy:2", str(good), "--registry", str(reg), "--window", "0:3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["version"] == "3" and out["parent_version"] == "2" and out["accept_novel"] is False
    assert out["records"][0]["name"].endswith("good.npz [0:3 s]") and out["records"][0]["n_samples"] == 300
    assert main(["update", "toy", str(bad), "--registry", str(reg), "--accept-novel", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["accept_novel"] is True and out["records"][0]["verdict"] == "novel" and out["parent_version"] == "3"
    cases = [
        (["update", "toy", str(tmp_path / "none.npz"), "--registry", str(reg)], "none.npz", 1),
        (["update", "nosuch", str(good), "--registry", str(reg)], "not found", 1),
        (["update", "toy", str(good), "--registry", str(reg), "--window", "3:1"], "--window", 2),
        (["update", "toy", str(good), "--registry", str(reg), "--version", "a/b"], "--version", 2),
        (["update", "toy", str(good), "--registry", str(reg), "--config", str(tmp_path / "x.toml")], "x.toml", 1),
        (["update", "toy", "--registry", str(reg)], "RECORD", 2),
    ]
    for argv, needle, code in cases:
        assert main(argv) == code, argv
        assert needle in capsys.readouterr().err, argv


# ------------------------------------------------------------------------------------------ with the config
SMALL = """
name = "bw-up"
[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"
[physics]
mass = 2.0
[model]
ny = 4
nu = 4
max_train_points = 200
restarts = 0
noise_calibration = "lags"
band_calibration = "lags"
[predict]
mc_paths = 32
method = "linear"
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 1 }
[[records]]
name = "lag-sweep"
roles = ["lags"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
[[records]]
name = "h1"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 2 }
[[records]]
name = "h2"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 3 }
"""


def test_update_with_the_config_recalibrates_noise_band_and_threshold(tmp_path):
    from gpnarx.training.config import load_config, simulate_record
    from gpnarx.training.pipeline import train
    from gpnarx.training.update import UpdateError, update

    path = tmp_path / "small.toml"
    path.write_text(SMALL)
    cfg = load_config(path)
    reg = tmp_path / "reg"
    trained = train(cfg, reg, report=False)
    parent = load_bundle(trained["path"])
    assert parent.manifest["noise_calibration"] and parent.manifest["band_discrepancy"] and parent.manifest["novelty"]
    new = simulate_record({"system": "bouc-wen", "excitation": "sweep", "amplitude": 35.0, "duration": 1.0,
                           "f0": 20.0, "f1": 60.0}, name="new-sweep")
    res = update(parent, [new], reg, config=cfg)
    man = load_bundle(res["path"]).manifest
    rec = man["lineage"]["recalibrated"]
    assert rec["noise"]["noise_var"] == man["noise_var"] and man["noise_calibration"]["n_records"] == 1
    assert rec["band"]["scale"] == man["band_discrepancy"]["scale"]
    assert rec["novelty"]["threshold"] == man["novelty"]["threshold"] and rec["novelty"]["records"] == 2
    assert man["novelty"]["calibration"]["records"] == ["h1", "h2"]
    assert man["n_train"] == 200 and man["lineage"]["rows"]["rows_dropped"] > 0  # the budget was full
    # a held-out record of the config cannot become a training record
    with pytest.raises(UpdateError, match="it is the config's held-out record 'lag-sweep'"):
        update(parent, cfg.records_for("lags"), reg, config=cfg)
    other = tmp_path / "other.toml"
    other.write_text(SMALL.replace("ny = 4", "ny = 6"))
    with pytest.raises(UpdateError, match="config: bw-up has ny=6, nu=4, the bundle ny=4, nu=4"):
        update(parent, [new], reg, config=load_config(other))


def test_a_sparse_model_is_refused_with_a_retrain(tmp_path, capsys):
    from gpnarx.training.update import UpdateError, update

    m = GPNARX(ny=2, nu=2, mode="sparse", n_inducing=16, max_train_points=100).fit([record(0, 200)], theta=theta(1.0))
    path = save_bundle(m, tmp_path, "sp", fs=FS, units={})
    with pytest.raises(UpdateError, match="model sp:1 has a sparse posterior.*needs a retrain"):
        update(load_bundle(path), [record(1, 200)], tmp_path)
    rec = write_npz(tmp_path / "r.npz", record(1, 200))
    assert main(["update", "sp", str(rec), "--registry", str(tmp_path)]) == 1
    assert "needs a retrain (gpnarx train)" in capsys.readouterr().err


def test_docs_updates_page_is_the_render_of_its_stored_run():
    """docs/updates.md's real-rig block is the render of docs/runs/update/bert-real-hold-19Hz.json, by code."""
    from gpnarx.training.pages.update import BEGIN, END, block, render_into

    root = Path(__file__).resolve().parents[1]
    rel = "docs/runs/update/bert-real-hold-19Hz.json"
    run = json.loads((root / rel).read_text())
    page = (root / "docs" / "updates.md").read_text()
    assert render_into(page, run, rel) == page, "docs/updates.md differs from the render of its stored run"
    rendered = block(run, rel)
    assert rendered.startswith(BEGIN) and rendered.endswith(END)
    for name in run["before"]:  # every validate record, before and after
        assert f"`{name}`" in rendered
    assert set(run["before"]) == set(run["after"]) and len(run["before"]) == 7


def test_partial_fit_takes_a_record_with_a_gap_as_fit_does():
    """A NaN run is a record break (model.gaps): no new row's window crosses it, and the envelope is finite."""
    m = fitted()
    r = record(1, 300)
    y = r.y.copy()
    y[100:110] = np.nan
    before = m.envelope_["n_records"]
    m.partial_fit([(r.u, y)])
    assert np.all(np.isfinite(m.posterior_.X_train)) and np.all(np.isfinite(targets(m.posterior_)))
    assert m.update_["new_regressor_rows"] == 300 - 2 - 12  # the 10 missing samples and the 2 rows after them
    assert np.isfinite(m.envelope_["y_peak"]) and m.envelope_["n_records"] == before + 2  # the two gap-free pieces
