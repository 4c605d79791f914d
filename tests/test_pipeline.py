"""Training pipeline, bundles, registry, lag surface and the CLI (issue 6)."""
import json
import shutil

import numpy as np
import pytest

from gpnarx.cli.main import main
from gpnarx.storage.bundle import BundleError, load_bundle, save_bundle
from gpnarx.storage.registry import Registry

SMALL_CONFIG = """
name = "bw-small"
[system]
fs = 750.0
units = {{ u = "N", y = "m" }}
output = "displacement"
[physics]
mass = 2.0
[model]
ny = {ny}
nu = {nu}
max_train_points = 300
restarts = 0
[lags]
ny = "2:4:2"
nu = "2:4:2"
[predict]
mc_paths = 32
[novelty]
false_alarm_rate = 0.05
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }}
noise = {{ fraction = 0.01, seed = 1 }}
[[records]]
name = "lag-sweep"
roles = ["lags", "verify"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }}
[[records]]
name = "h1"
roles = ["healthy"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }}
noise = {{ fraction = 0.01, seed = 2 }}
[[records]]
name = "h2"
roles = ["healthy"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }}
noise = {{ fraction = 0.01, seed = 3 }}
"""


@pytest.fixture(scope="module")
def small_config(tmp_path_factory):
    d = tmp_path_factory.mktemp("cfg")
    p = d / "small.toml"
    p.write_text(SMALL_CONFIG.format(ny=4, nu=4))
    return p


@pytest.fixture(scope="module")
def trained(small_config, tmp_path_factory):
    reg = tmp_path_factory.mktemp("registry")
    rc = main(["train", str(small_config), "--registry", str(reg), "--json"])
    assert rc == 0
    return reg


def test_train_writes_bundle_and_report(trained):
    b = load_bundle(trained / "bw-small" / "1")
    m = b.manifest
    assert m["lags"] == {"ny": 4, "nu": 4} and m["fs"] == 750.0 and m["units"] == {"u": "N", "y": "m"}
    assert m["novelty"]["false_alarm_rate"] == 0.05
    # the threshold is the 95 % quantile of the log-normal fit to the healthy records' scores (as scored
    # in the training metrics), never below the largest of them with fewer than 1 / 0.05 records
    from scipy.special import ndtri

    scores = np.array([m["training"]["records"][h]["novelty_score"] for h in ("h1", "h2")])
    logs = np.log(scores)
    expect = max(float(np.exp(logs.mean() + ndtri(0.95) * logs.std(ddof=1))), float(scores.max()))
    assert m["novelty"]["threshold"] == pytest.approx(expect, rel=1e-9)
    env = m["novelty"]["envelope"]
    assert 0 < env["u"][0] <= env["u"][1] and 0 < env["y"][0] <= env["y"][1]
    assert set(m["training"]["records"]) == {"lag-sweep", "h1", "h2"}
    assert m["training"]["records"]["lag-sweep"]["fit"] > 50
    assert all(len(v) == 64 for v in m["files"].values())
    rep = json.loads((trained / "bw-small" / "1" / "report" / "report.json").read_text())
    assert {r["name"] for r in rep["records"]} >= {"lag-sweep", "h1"}
    assert (trained / "bw-small" / "1" / "report" / "report.html").is_file()
    assert list((trained / "bw-small" / "1" / "report").glob("*.png"))


def test_record_with_two_roles_is_simulated_once(small_config, tmp_path, monkeypatch):
    """lag-sweep has roles lags and verify: one free run, reported under both roles."""
    import gpnarx.training.pipeline as pl

    calls = []
    real = pl.evaluate_record

    def counting(model, rec, role, *a, **kw):
        calls.append((rec.name, role))
        return real(model, rec, role, *a, **kw)

    monkeypatch.setattr(pl, "evaluate_record", counting)
    res = pl.train(small_config, tmp_path, report=False, mc_paths=8)
    assert [c for c in calls if c[0] == "lag-sweep"] == [("lag-sweep", "lags")]
    assert sorted(name for name, _ in calls) == ["h1", "h2", "lag-sweep"]
    roles = [(ev["name"], ev["role"]) for ev in res["evals"]]
    assert ("lag-sweep", "lags") in roles and ("lag-sweep", "verify") in roles
    lag, ver = (ev for ev in res["evals"] if ev["name"] == "lag-sweep")
    assert lag["metrics"] == ver["metrics"] and lag["metrics"]["fit"] > 50


def test_versions_increase_and_are_never_overwritten(trained):
    b = load_bundle(trained / "bw-small" / "1")
    p2 = save_bundle(b.model, trained, "bw-small", fs=750.0, units=b.manifest["units"])
    assert p2.name == "2"
    with pytest.raises(BundleError, match="already exists"):
        save_bundle(b.model, trained, "bw-small", version="2", fs=750.0, units=b.manifest["units"])
    shutil.rmtree(p2)


def test_bundle_round_trip_predicts_identically(trained, tmp_path):
    b = load_bundle(trained / "bw-small" / "1")
    p = save_bundle(b.model, tmp_path, "copy", fs=750.0, units={"u": "N", "y": "m"})
    b2 = load_bundle(p)
    u = np.sin(np.linspace(0, 20, 300)) * 30
    r1 = b.model.simulate(u, n_paths=64, seed=3)
    r2 = b2.model.simulate(u, n_paths=64, seed=3)
    assert np.max(np.abs(r1.mean - r2.mean)) <= 1e-12 * np.max(np.abs(r1.mean))
    assert np.max(np.abs(r1.upper - r2.upper)) <= 1e-12 * np.max(np.abs(r1.upper))


def test_flipped_byte_in_any_array_is_refused_and_rest_loads(trained, tmp_path):
    src = trained / "bw-small" / "1"
    reg = tmp_path / "reg"
    for name in ("good", "bad"):
        b = load_bundle(src)
        save_bundle(b.model, reg, name, fs=750.0, units={"u": "N", "y": "m"})
    bad = reg / "bad" / "1"
    for npy in sorted(bad.glob("*.npy")):
        data = bytearray(npy.read_bytes())
        original = bytes(data)
        data[len(data) // 2] ^= 0x01
        npy.write_bytes(bytes(data))
        with pytest.raises(BundleError, match=npy.name):
            load_bundle(bad)
        r = Registry(reg).scan()
        assert r.names() == ["good"]
        assert len(r.refused) == 1 and npy.name in r.refused[0]["reason"]
        npy.write_bytes(original)
    assert Registry(reg).scan().names() == ["bad", "good"]


def test_changed_manifest_and_unsafe_names_are_refused(trained, tmp_path):
    b = load_bundle(trained / "bw-small" / "1")
    p = save_bundle(b.model, tmp_path, "m", fs=750.0, units={"u": "N", "y": "m"})
    mf = json.loads((p / "manifest.json").read_text())
    mf["files"]["../../etc/passwd"] = "0" * 64
    (p / "manifest.json").write_text(json.dumps(mf))
    with pytest.raises(BundleError, match="manifest edited"):
        load_bundle(p)
    import hashlib

    (p / "manifest.sha256").write_text(hashlib.sha256((p / "manifest.json").read_bytes()).hexdigest())
    with pytest.raises(BundleError, match="not allowed"):  # even with a matching checksum
        load_bundle(p)
    mf["files"].pop("../../etc/passwd")
    mf["fs"] = 751.0
    (p / "manifest.json").write_text(json.dumps(mf))
    with pytest.raises(BundleError, match="manifest.json: sha256 does not match"):
        load_bundle(p)
    (p / "manifest.sha256").unlink()
    with pytest.raises(BundleError, match="missing"):
        load_bundle(p)
    for bad in ("../x", "a/b", "", ".hidden"):
        with pytest.raises(BundleError):
            save_bundle(b.model, tmp_path, bad, fs=750.0, units={})


def test_predict_and_novelty_cli_json(trained, small_config, tmp_path, capsys):
    rec = tmp_path / "r.npz"
    assert main(["simulate", "bouc-wen", "--excitation", "sweep", "--amplitude", "35", "--f0", "20", "--f1", "60",
                 "--duration", "0.5", "--out", str(rec)]) == 0
    capsys.readouterr()
    assert main(["predict", "--registry", str(trained), "--model", "bw-small", str(rec), "--mc", "64", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"mean", "lower", "upper", "std", "fit", "rmse", "coverage"} <= set(out)
    assert len(out["mean"]) == 375 and out["fit"] > 50
    with np.load(rec) as d:  # coverage: the measured samples inside the answer's own band
        inside = (d["y"] >= np.array(out["lower"])) & (d["y"] <= np.array(out["upper"]))
    assert out["coverage"] == pytest.approx(100 * inside.mean())
    assert main(["novelty", "--registry", str(trained), "--model", "bw-small:1", str(rec), "--mc", "64", "--json"]) == 0
    nov = json.loads(capsys.readouterr().out)
    assert nov["verdict"] in ("healthy", "novel") and nov["false_alarm_rate"] == 0.05 and nov["score"] > 0
    assert isinstance(nov["out_of_range"], list)
    assert nov["verdict"] == ("novel" if nov["score"] > nov["threshold"] or nov["out_of_range"] else "healthy")
    # a record 1000x larger than every healthy calibration record leaves the envelope; its drive is then
    # not the probe either, so it is unjudged (model.novelty.verdict: the probe comes first)
    big = tmp_path / "big.npz"
    with np.load(rec) as d:
        np.savez(big, u=d["u"] * 1000, y=d["y"] * 1000, fs=d["fs"])
    assert main(["novelty", "--registry", str(trained), "--model", "bw-small:1", str(big), "--mc", "16", "--json"]) == 0
    far = json.loads(capsys.readouterr().out)
    # ... and its drive (1000x the healthy amplitude) is not the probe the threshold holds for
    assert far["out_of_range"] == ["u", "y", "prediction", "frequency", "probe"] and far["verdict"] == "unjudged", far
    assert far["diverged_paths"] == 16 and far["start"] == "measured", far  # 1000x the training peak: every path


def test_predict_and_novelty_cli_window_and_measured_start(trained, tmp_path, capsys):
    rec = tmp_path / "r.npz"
    assert main(["simulate", "bouc-wen", "--excitation", "sine", "--amplitude", "35", "--freq", "40",
                 "--duration", "1.0", "--out", str(rec)]) == 0
    capsys.readouterr()
    base = ["--registry", str(trained), "--model", "bw-small", str(rec), "--mc", "32", "--json"]
    assert main(["predict", *base, "--window", "0.4:0.8"]) == 0
    rest = json.loads(capsys.readouterr().out)
    assert len(rest["mean"]) == 300 and rest["start"] == "rest"  # 0.4 s at 750 Hz
    assert main(["predict", *base, "--window", "0.4:0.8", "--start", "measured"]) == 0
    meas = json.loads(capsys.readouterr().out)
    with np.load(rec) as d:
        y = d["y"][300:600]
    assert meas["start"] == "measured" and len(meas["mean"]) == 300
    assert np.allclose(meas["mean"][:4], y[:4])  # ny = 4 measured outputs start the free run
    assert not np.allclose(rest["mean"][:4], y[:4], rtol=0.1)  # from rest they are predicted, near 0
    # mid-oscillation, a run from the measured state tracks the record better than one from rest
    assert meas["fit"] > rest["fit"]
    assert "novelty_score" not in rest  # a run from rest is not scored by the novelty rule
    assert main(["novelty", *base, "--window", "0.4:0.8"]) == 0
    nov = json.loads(capsys.readouterr().out)
    assert nov["score"] > 0 and nov["verdict"] in ("healthy", "novel", "unjudged")
    assert (nov["verdict"] == "unjudged") == (nov["probe_match"] is False)  # a drive off the probe is not judged
    assert "novelty_score" not in meas  # predict answers as HTTP predict does: the score is gpnarx novelty's


def test_segment_median_novelty_method_reaches_bundle_cli_and_service(small_config, tmp_path, capsys):
    """A config choosing the spike-robust score: the threshold, the CLI and the service all use it."""
    from fastapi.testclient import TestClient

    from gpnarx.model.novelty import SEGMENT_METHOD, novelty_score, novelty_start
    from gpnarx.service.app import create_app

    cfg = tmp_path / "seg.toml"
    cfg.write_text(small_config.read_text().replace("false_alarm_rate = 0.05",
                                                    f'false_alarm_rate = 0.05\nmethod = "{SEGMENT_METHOD}"'))
    reg = tmp_path / "reg"
    assert main(["train", str(cfg), "--registry", str(reg), "--no-report", "--json"]) == 0
    capsys.readouterr()
    b = load_bundle(reg / "bw-small" / "1")
    nov = b.manifest["novelty"]
    assert nov["method"] == SEGMENT_METHOD
    # the stored healthy scores are segment-median scores of the healthy records' own predictions
    h1 = b.manifest["training"]["records"]["h1"]
    assert h1["novelty_score"] == pytest.approx(nov["healthy_scores"][0])
    rec = tmp_path / "r.npz"
    assert main(["simulate", "bouc-wen", "--excitation", "sweep", "--amplitude", "30", "--f0", "20", "--f1", "60",
                 "--duration", "0.5", "--seed", "5", "--out", str(rec)]) == 0
    capsys.readouterr()
    assert main(["novelty", "--registry", str(reg), "--model", "bw-small", str(rec), "--mc", "32", "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert cli["score_method"] == SEGMENT_METHOD
    with np.load(rec) as d:
        u, y = d["u"], d["y"]
    run = b.model.simulate(u, n_paths=32, seed=0, y0=novelty_start(y, b.model.ny))
    assert cli["score"] == pytest.approx(novelty_score(y, run.mean, run.std, SEGMENT_METHOD)["score"], rel=1e-9)
    with TestClient(create_app(reg)) as client:
        r = client.post("/v1/models/bw-small/novelty", json={"u": u.tolist(), "y": y.tolist(), "fs": 750.0,
                                                             "mc_paths": 32, "seed": 0})
    assert r.status_code == 200, r.text
    assert r.json()["score_method"] == SEGMENT_METHOD and r.json()["score"] == pytest.approx(cli["score"], rel=1e-9)


# exit code 2: the command line itself is wrong; 1: the work failed (unknown model, unreadable record or config)
@pytest.mark.parametrize("argv, needle, code", [
    (["predict", "--registry", "{reg}", "--model", "bw-small", "{rec}", "--window", "2"], "--window must be START:END",
     2),
    (["predict", "--registry", "{reg}", "--model", "bw-small", "{rec}", "--window", "0.05:0.01"], "START < END", 2),
    (["novelty", "--registry", "{reg}", "--model", "bw-small", "{rec}", "--window", "0:9"], "outside the record", 1),
    (["predict", "--registry", "{reg}", "--model", "nope", "{rec}"], "not found", 1),
    (["predict", "--registry", "{reg}", "--model", "../etc", "{rec}"], "invalid", 2),
    (["predict", "--registry", "{reg}", "--model", "bw-small", "{missing}"], "missing.npz", 1),
    (["train", "{badcfg}", "--registry", "{reg}"], "name", 1),
    (["train", "{reg}/nothing.toml", "--registry", "{reg}"], "nothing.toml", 1),
    (["lags", "{cfg}", "--ny", "x:y", "--out", "{reg}/s.json"], "ny", 2),
])
def test_cli_errors_are_one_line_with_their_exit_code(argv, needle, code, trained, small_config, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[system]\nfs = 750.0\n")
    rec = tmp_path / "r.csv"
    rec.write_text("time,u,y\n" + "\n".join(f"{i / 750},{np.sin(i)},{0.0}" for i in range(50)))
    fmt = {"reg": str(trained), "rec": str(rec), "missing": str(tmp_path / "missing.npz"), "badcfg": str(bad),
           "cfg": str(small_config)}
    rc = main([a.format(**fmt) for a in argv])
    err = capsys.readouterr().err
    assert rc == code, err
    assert len(err.strip().splitlines()) == 1, err
    assert needle in err


def test_lag_surface_joblib_resumes_and_matches_dask(small_config, tmp_path):
    from gpnarx.training.lags import choose_lags, lag_surface

    # two cells (ny 2 and 4 at nu 4): one per joblib worker and per Dask worker
    s1 = lag_surface(small_config, [2, 4], [4], jobs=2, cache_dir=tmp_path / "c1")
    assert s1["cached_cells"] == 0 and len(s1["cells"]) == 2
    for c in s1["cells"]:  # per-record fits are kept; the cell's fit is their mean
        assert set(c["fits"]) == {"lag-sweep"}
        assert c["fit"] == pytest.approx(np.mean(list(c["fits"].values())))
    again = lag_surface(small_config, [2, 4], [4], jobs=2, cache_dir=tmp_path / "c1")
    assert again["cached_cells"] == 2 and again["cells"] == s1["cells"]
    from dask.distributed import LocalCluster

    # workers as threads of this process (no worker processes to start); tests/test_dask_cluster.py runs
    # the lag surface on worker processes that cannot read a path
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        s2 = lag_surface(small_config, [2, 4], [4], scheduler=cluster.scheduler_address, cache_dir=tmp_path / "c2")
    f1 = [(c["ny"], c["nu"], c["fit"]) for c in s1["cells"]]
    f2 = [(c["ny"], c["nu"], c["fit"]) for c in s2["cells"]]
    assert [a[:2] for a in f1] == [b[:2] for b in f2]
    assert np.allclose([a[2] for a in f1], [b[2] for b in f2], atol=1e-9)
    ch = choose_lags(s1["cells"])
    best = max(c["fit"] for c in s1["cells"])
    assert ch["fit"] >= best - 0.5


def test_choose_lags_rule():
    from gpnarx.training.lags import choose_lags

    cells = [{"ny": 20, "nu": 17, "fit": 92.4}, {"ny": 10, "nu": 8, "fit": 92.1}, {"ny": 4, "nu": 4, "fit": 80.0},
             {"ny": 12, "nu": 6, "fit": 92.0}]
    assert choose_lags(cells) == {"ny": 10, "nu": 8, "fit": 92.1}
    assert choose_lags(cells, tolerance=0.1)["ny"] == 20


def test_lags_cli_writes_surface_and_png(small_config, tmp_path, capsys):
    out = tmp_path / "surface.json"
    assert main(["lags", str(small_config), "--ny", "2:4:2", "--nu", "2:2", "--jobs", "1", "--out", str(out),
                 "--cache-dir", str(tmp_path / "cache"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    data = json.loads(out.read_text())
    assert res["cells"] == len(data["cells"]) == 2
    # the chosen cell is the rule's pick on the surface this run wrote: the smallest ny + nu within the
    # tolerance of the best fit (here the two cells differ by ny only)
    best = max(c["fit"] for c in data["cells"])
    near = [c for c in data["cells"] if c["fit"] >= best - data["tolerance"]]
    pick = min(near, key=lambda c: c["ny"] + c["nu"])
    assert (res["chosen"]["ny"], res["chosen"]["nu"]) == (pick["ny"], pick["nu"])
    assert res["chosen"]["fit"] == pytest.approx(pick["fit"])
    assert out.with_suffix(".png").is_file()


def test_grid_edge_names_the_axes_where_the_best_cell_is_the_largest_tried():
    from gpnarx.training.lags import grid_edge

    assert grid_edge({"ny": 24, "nu": 10}, [2, 8, 24], [2, 10, 20]) == ["ny"]
    assert grid_edge({"ny": 24, "nu": 20}, [2, 8, 24], [2, 10, 20]) == ["ny", "nu"]
    assert grid_edge({"ny": 8, "nu": 10}, [2, 8, 24], [2, 10, 20]) == []
    assert grid_edge({"ny": 2, "nu": 20}, [2, 8, 24], [20]) == []  # a fixed axis is not an edge


def test_lags_cli_warns_when_the_best_cell_is_on_the_grid_edge(small_config, tmp_path, capsys, monkeypatch):
    import gpnarx.training.lags as lags_mod

    def fake_cell(config_path, ny, nu, settings):  # fit rises with ny, peaks inside the nu range
        return {"ny": ny, "nu": nu, "fit": 80.0 + ny - abs(nu - 4), "fits": {}, "seconds": 0.0}

    monkeypatch.setattr(lags_mod, "lag_cell", fake_cell)
    out = tmp_path / "surface.json"
    assert main(["lags", str(small_config), "--ny", "2:6:2", "--nu", "2:6:2", "--jobs", "1", "--out", str(out),
                 "--cache-dir", str(tmp_path / "cache"), "--json"]) == 0
    cap = capsys.readouterr()
    res = json.loads(cap.out)
    assert res["best"] == {"ny": 6, "nu": 4, "fit": 86.0} and res["edge"] == ["ny"]
    assert "warning" in cap.err and "largest ny=6 tried" in cap.err and "--ny" in cap.err
    assert json.loads(out.read_text())["edge"] == ["ny"]
    # the best cell inside the grid: no warning
    out2 = tmp_path / "surface2.json"
    monkeypatch.setattr(lags_mod, "lag_cell", lambda c, ny, nu, s: {"ny": ny, "nu": nu, "fit": 90.0 - abs(ny - 4)
                                                                     - abs(nu - 4), "fits": {}, "seconds": 0.0})
    assert main(["lags", str(small_config), "--ny", "2:6:2", "--nu", "2:6:2", "--jobs", "1", "--out", str(out2),
                 "--cache-dir", str(tmp_path / "cache3"), "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["edge"] == [] and "warning" not in cap.err


def test_noise_calibration_on_the_lags_record_reaches_the_bundle(tmp_path):
    from gpnarx.training.pipeline import train

    p = tmp_path / "cal.toml"
    p.write_text(SMALL_CONFIG.format(ny=4, nu=4).replace("restarts = 0", "restarts = 0\nnoise_calibration = \"lags\""))
    logs = []
    out = train(p, tmp_path / "reg", report=False, mc_paths=8, baselines={}, log=logs.append)
    nc = out["model"].noise_calibration_
    # lag-sweep (1 s at 750 Hz, ny = nu = 4) is the held-out record
    assert nc["n_records"] == 1 and nc["n_residuals"] == 750 - 4
    assert out["model"].noise_var_ == nc["noise_var"]
    # the calibrated value is the held-out ML estimate from the ML-II model's one-step residuals on
    # lag-sweep, floored at ML-II's sigma_y^2: recomputed here from a model fitted without calibration
    from gpnarx.model.heldout_noise import heldout_noise_var
    from gpnarx.model.regressors import stack_regressors
    from gpnarx.training.config import load_config
    from gpnarx.training.prepare import model_from_config

    cfg = load_config(p)
    plain = model_from_config(cfg, None, None).fit(cfg.records_for("train"))
    assert nc["noise_var_ml2"] == pytest.approx(plain.noise_var_, rel=1e-9)
    held = cfg.records_for("lags")[0]
    X, Y, _ = stack_regressors([(held.u, held.y)], 4, 4)
    mu, var = plain.posterior_.predict(plain.x_scaler_.transform(X))
    resid = (Y - plain.y_scaler_.mean_[0]) / plain.y_scaler_.scale_[0] - mu
    assert nc["noise_var"] == pytest.approx(heldout_noise_var(resid, var, floor=plain.noise_var_), rel=1e-6)
    assert any("noise calibrated on 1 held-out 'lags' record(s)" in m for m in logs), logs
    manifest = load_bundle(out["path"]).manifest
    assert manifest["noise_calibration"] == pytest.approx(nc)
    assert manifest["noise_var"] == pytest.approx(nc["noise_var"])


def test_train_overrides_mode_and_training_points_from_the_command_line(small_config, tmp_path, capsys):
    """`gpnarx train CONFIG --mode exact --train-points N` trains the config's model as the full GP on N rows
    (the bundle says so); a count under 2 is refused naming the option."""
    reg = tmp_path / "reg"
    assert main(["train", str(small_config), "--registry", str(reg), "--no-report", "--mode", "exact",
                 "--train-points", "120", "--json"]) == 0
    capsys.readouterr()
    b = load_bundle(reg / "bw-small" / "1")
    assert b.manifest["mode"] == "exact" and b.manifest["n_train"] == 120
    assert b.model.posterior_.kind == "exact" and b.model.posterior_.n_points == 120
    assert main(["train", str(small_config), "--registry", str(reg), "--train-points", "1"]) != 0
    assert "--train-points must be at least 2" in capsys.readouterr().err
