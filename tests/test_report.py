import base64
import json
import math
import re

import numpy as np
import pytest

from gpnarx.model.restoring import loop_area, restoring_force
from gpnarx.training import report as rp
from gpnarx.training import report_figures as rf
from gpnarx.training import report_metrics as rmet

FS = 256.0


def _sine_record(name="sine_low", f0=18.0, n=1024, noise=0.05, seed=0, perfect=False, half=0.1, **kw):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    u = np.sin(2 * np.pi * f0 * t)
    clean = 1e-3 * (np.sin(2 * np.pi * f0 * t - 0.3) + 0.1 * np.sin(2 * np.pi * 3 * f0 * t))
    y = clean + noise * 1e-3 * rng.normal(size=n)
    mean = y.copy() if perfect else clean
    rec = {"name": name, "role": "validation", "fs": FS, "t": t, "u": u, "y": y, "y_clean": clean,
           "mean": mean, "lower": mean - half * 1e-3, "upper": mean + half * 1e-3,
           "units": {"u": "N", "y": "m"}, "metrics": {"noise_std": noise * 1e-3}}
    rec.update(kw)
    return rec


def _surface():
    return [{"ny": ny, "nu": nu, "fit": 90.0 - abs(ny - 8) - 0.5 * abs(nu - 6)}
            for ny in range(2, 13, 2) for nu in range(2, 11, 2)]


def test_record_metrics_values():
    rec = _sine_record(perfect=True)
    m = rmet.record_metrics(rec, None)
    assert m["fit"] == pytest.approx(100.0)
    assert m["rmse"] == pytest.approx(0.0, abs=1e-15)
    assert m["coverage"] == pytest.approx(100.0)
    assert m["band_width"] == pytest.approx(0.2e-3)
    assert m["psd_peaks_measured"][0] == pytest.approx(18.0, abs=1.0)
    assert m["psd_peaks_predicted"][0] == pytest.approx(18.0, abs=1.0)
    assert "fit_clean" in m and "coverage_clean" not in m
    assert "coverage_latent" not in m  # no latent band given: the noise-free output is not scored for coverage

    # coverage computed by hand: half of the samples moved outside the band
    rec2 = _sine_record(noise=0.0)
    rec2["upper"] = rec2["mean"] + 1e-4
    rec2["lower"] = rec2["mean"] - 1e-4
    rec2["upper"][::2] = rec2["y"][::2] - 1e-6  # every other sample above the band
    m2 = rmet.record_metrics(rec2, None)
    assert m2["coverage"] == pytest.approx(50.0)
    expect_fit = 100 * (1 - np.linalg.norm(rec2["y"] - rec2["mean"]) / np.linalg.norm(rec2["y"]))
    assert m2["fit"] == pytest.approx(expect_fit)
    assert m2["fit_clean"] == pytest.approx(100.0)


def test_harmonics_and_physics_metrics():
    rec = _sine_record(drive_freq=18.0, n=2048)
    phys = {"mass": 2.0, "input_gain": 1.0, "output": "displacement"}
    m = rmet.record_metrics(rec, phys)
    hm, hp = m["harmonics_db_measured"], m["harmonics_db_predicted"]
    assert len(hm) == 3 and len(hp) == 3
    assert hm[0] > hm[2] > hm[1]  # 3rd harmonic present, 2nd absent (only noise)
    assert hp[0] == pytest.approx(hm[0], abs=0.5)
    x, r = restoring_force(rec["u"], rec["mean"], FS, 2.0)
    assert m["loop_area_predicted"] == pytest.approx(loop_area(x, r))
    assert m["loop_area_measured"] > 0
    # the noise-free loop (the paper's reference for simulated records) is scored on its own
    xc, rc = restoring_force(rec["u"], rec["y_clean"], FS, 2.0)
    assert m["loop_area_clean"] == pytest.approx(loop_area(xc, rc))
    xm, rm = restoring_force(rec["u"], rec["y"], FS, 2.0)
    assert m["loop_area_measured"] == pytest.approx(loop_area(xm, rm))
    assert m["loop_area_clean"] != pytest.approx(m["loop_area_measured"], rel=1e-6)


def test_report_table_has_noise_free_loop_column_only_when_known(tmp_path):
    phys = {"mass": 2.0, "input_gain": 1.0, "output": "displacement"}
    with_clean = rp.write_report(tmp_path / "a", "a", {}, [_sine_record(n=1024)], physics=phys)
    assert "loop area noise-free" in with_clean["html"].read_text()
    rec = _sine_record(n=1024)
    rec["y_clean"] = None
    without = rp.write_report(tmp_path / "b", "b", {}, [rec], physics=phys)
    assert "loop area noise-free" not in without["html"].read_text()
    assert "loop_area_clean" not in json.loads(without["json"].read_text())["records"][0]["metrics"]


def test_write_report_full(tmp_path):
    recs = [_sine_record("sine_low", perfect=True, drive_freq=18.0),
            _sine_record("sweep <med> & co", f0=30.0, seed=1, zoom=(1.0, 1.5))]
    baselines = {"sine_low": {"ARX": {"fit": 80.0, "rmse": 1e-4}, "NARX-poly": {"fit": 120.0 - 30}},
                 "sweep <med> & co": {"ARX": {"fit": 99.9}, "NARX-poly": {"fit": float("nan")}}}
    paper = {"lags": {"ny": 8, "nu": 6, "fit": 92.4}, "records": {"sine_low": {"fit": 95.1}}}
    paths = rp.write_report(tmp_path / "rep", "Test <report>", {"n_train": 1000, "kernel": {"name": "rq", "nu": None},
                                                                  "bad": float("nan")},
                            recs, physics=None, lag_surface={"surface": _surface(), "chosen": (8, 6)},
                            baselines=baselines, paper=paper)
    for key in ("json", "html", "lag_surface"):
        assert paths[key].exists() and paths[key].stat().st_size > 0
    for name in ("sine_low", "sweep <med> & co"):
        p = paths["records"][name]
        assert p.exists() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = paths["json"].read_text()
    assert "NaN" not in text and "Infinity" not in text
    rep = json.loads(text)
    assert rep["title"] == "Test <report>"
    assert rep["summary"]["bad"] is None
    r0 = rep["records"][0]
    assert r0["name"] == "sine_low"
    assert r0["metrics"]["fit"] == pytest.approx(100.0)
    assert r0["metrics"]["coverage"] == pytest.approx(100.0)
    assert r0["metrics"]["noise_std"] == pytest.approx(5e-5)  # caller-supplied metric kept
    assert len(r0["metrics"]["harmonics_db_measured"]) == 3
    assert all(not isinstance(v, list) or len(v) <= 3 for v in r0["metrics"].values())
    assert rep["lag_surface"]["chosen"] == [8, 6]
    assert rep["lag_surface"]["paper"] == [8, 6, 92.4]
    assert rep["lag_surface"]["best"]["fit"] == pytest.approx(90.0)
    assert rep["lag_surface"]["edge"] == []  # the best cell (8, 6) is inside the grid
    assert len(rep["lag_surface"]["table"]) == len(_surface())
    assert rep["baselines"]["sweep <med> & co"]["NARX-poly"]["fit"] is None
    assert rep["comparison"]["sine_low"]["best"] == "GP-NARX"
    assert rep["comparison"]["sweep <med> & co"]["best"] == "ARX"
    assert rep["paper"]["records"]["sine_low"]["fit"] == 95.1

    html_text = paths["html"].read_text()
    assert "sine_low" in html_text
    assert "sweep &lt;med&gt; &amp; co" in html_text and "sweep <med>" not in html_text
    assert "Test &lt;report&gt;" in html_text
    for model in ("GP-NARX", "ARX", "NARX-poly"):
        assert model in html_text
    assert "95.1" in html_text  # paper column
    assert "lag_surface.png" in html_text
    # figures are embedded (a copied report opens on its own); the PNG files stay next to it
    srcs = re.findall(r"<img src='([^']*)' data-file='([^']*)'", html_text)
    assert sorted(fn for _, fn in srcs) == sorted(["lag_surface.png", *(p.name for p in paths["records"].values())])
    for src, fn in srcs:
        assert src == "data:image/png;base64," + base64.b64encode((paths["html"].parent / fn).read_bytes()).decode()
    text = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]*", "", html_text)
    assert "NaN" not in text and "nan" not in text.lower().replace("nanjing", "")


def test_velocity_physics_and_prediction_only(tmp_path):
    n = 1024
    t = np.arange(n) / FS
    f0 = 20.0
    u = 5 * np.sin(2 * np.pi * f0 * t)
    vel = 1e-2 * np.cos(2 * np.pi * f0 * t)
    rec_v = {"name": "vel", "role": "test", "fs": FS, "u": u, "y": vel, "mean": 0.98 * vel,
             "lower": 0.98 * vel - 1e-3, "upper": 0.98 * vel + 1e-3, "units": {"u": "N", "y": "m/s"},
             "drive_freq": f0}
    phys = {"mass": 0.5, "output": "velocity"}
    m = rmet.record_metrics(rec_v, phys)
    assert m["fit"] == pytest.approx(98.0)
    assert m["loop_area_measured"] > 0 and m["loop_area_predicted"] > 0
    rec_p = {"name": "pred_only", "role": "prediction", "fs": FS, "u": u, "y": None, "mean": vel,
             "lower": vel - 1e-3, "upper": vel + 1e-3, "units": {"u": "N", "y": "m/s"}}
    mp = rmet.record_metrics(rec_p, phys)
    assert "fit" not in mp and "coverage" not in mp
    assert mp["band_width"] == pytest.approx(2e-3)
    assert "loop_area_predicted" in mp and "loop_area_measured" not in mp
    assert "psd_peaks_measured" not in mp and mp["psd_peaks_predicted"][0] == pytest.approx(f0, abs=1.0)
    paths = rp.write_report(tmp_path, "vel", {}, [rec_v, rec_p], physics=phys)
    assert paths["lag_surface"] is None
    assert all(p.exists() for p in paths["records"].values())
    rep = json.loads(paths["json"].read_text())
    assert [r["name"] for r in rep["records"]] == ["vel", "pred_only"]
    assert rep["records"][1]["metrics"].get("fit") is None
    html_text = paths["html"].read_text()
    assert "vel" in html_text and "pred_only" in html_text
    # no physics: the loop panel falls back to y vs u; short record (< 512 samples) PSD over the whole record
    short = _sine_record("short", n=200)
    p = rf.record_figure(short, None, tmp_path / "short.png")
    assert p.exists()


def test_lag_surface_figure(tmp_path):
    p = rf.lag_surface_figure(_surface(), (8, 6), (20, 17, 92.4), tmp_path / "sub" / "lag.png")
    assert p.exists() and p.stat().st_size > 1000
    rows = [{"ny": 4, "nu": 4, "fit": float("nan")}, {"ny": 4, "nu": 6, "fit": 50.0}]
    p2 = rf.lag_surface_figure(rows, {"ny": 4, "nu": 6}, {"ny": 4, "nu": 4, "fit": 60.0}, tmp_path / "lag2.png")
    assert p2.exists()
    # training.lags output layout ("cells", chosen as a dict, NaN fits with an error message)
    rows.append({"ny": 6, "nu": 4, "fit": float("nan"), "error": "singular"})
    paths = rp.write_report(tmp_path / "r", "lags", {}, [], lag_surface={"cells": rows, "chosen": {"ny": 4, "nu": 6}})
    rep = json.loads(paths["json"].read_text())
    assert rep["lag_surface"]["chosen"] == [4, 6] and rep["lag_surface"]["best"]["fit"] == 50.0
    assert rep["lag_surface"]["edge"] == ["nu"]  # best at nu=6, the largest tried
    assert "lag grid edge" in paths["html"].read_text()
    assert rep["lag_surface"]["table"][0]["fit"] is None and rep["lag_surface"]["table"][2]["error"] == "singular"
    assert paths["lag_surface"].exists()


def test_lag_surface_marks_outline_the_cell_and_leave_its_label_visible(tmp_path, monkeypatch):
    """The chosen (and paper's) cell is outlined along the cell's edges, not covered by a marker at its centre,
    so its own fit label stays readable; a cell off the grid still gets a marker."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    figs = []
    monkeypatch.setattr(rf.plt, "close", lambda fig=None: figs.append(fig))
    surface = [{"ny": a, "nu": b, "fit": 50.0 + a + b} for a in (4, 8, 12) for b in (2, 6, 10)]
    rf.lag_surface_figure(surface, (8, 6), (12, 10, 70.0), tmp_path / "lag.png")
    ax = figs[-1].axes[0]
    boxes = {p.get_label(): p for p in ax.patches if isinstance(p, Rectangle)}
    chosen = boxes["chosen ny=8, nu=6 (64.0 %)"]
    assert (chosen.get_x(), chosen.get_y(), chosen.get_width(), chosen.get_height()) == (4.0, 6.0, 4.0, 4.0)
    label = next(t for t in ax.texts if t.get_position() == (6.0, 8.0))
    assert label.get_text() == "64.0"  # the label is drawn at the cell's centre, inside the outline
    assert not [ln for ln in ax.lines if list(ln.get_xdata()) == [6]]  # no marker on top of it
    assert rf.cell_box(np.array([2.0, 6.0, 10.0]), np.array([4.0, 8.0, 12.0]), 10, 12, inset=0.25) == (
        9.0, 11.0, 2.0, 2.0)
    rf.lag_surface_figure(surface, (8, 6), (20, 17, 92.4), tmp_path / "lag2.png")  # the paper's cell off the grid
    assert [ln.get_label() for ln in figs[-1].axes[0].lines] == ["paper ny=20, nu=17 (92.4 %)"]
    monkeypatch.undo()
    for fig in figs:
        plt.close(fig)


def test_json_sanitiser():
    out = rmet.to_report_json({"a": np.float64("nan"), "b": np.arange(3), "c": np.zeros(1000), "d": (1, np.int64(2)),
                        "e": math.inf})
    assert out == {"a": None, "b": [0, 1, 2], "c": {"omitted_array_shape": [1000]}, "d": [1, 2], "e": None}
    json.dumps(out, allow_nan=False)


def test_coverage_two_ways_predictive_vs_measured_and_latent_vs_noise_free(tmp_path):
    """The predictive band (noise included) is scored against the measured output only, the latent band
    (no noise term) against the noise-free one: a band wide enough for the noise must not lend the
    noise-free output its coverage (issue 22)."""
    rec = _sine_record(noise=0.5, half=1.0)  # predictive half-width 1e-3, noise sd 5e-4
    clean = rec["y_clean"]
    rec["latent_lower"], rec["latent_upper"] = rec["mean"] - 1e-5, rec["mean"] + 1e-5
    rec["latent_lower"][::4] = clean[::4] + 1e-9  # a quarter of the noise-free samples below the latent band
    m = rmet.record_metrics(rec, None)
    inside = (rec["y"] >= rec["lower"]) & (rec["y"] <= rec["upper"])
    assert m["coverage"] == pytest.approx(100 * inside.mean()) and m["coverage"] < 100
    assert m["coverage_latent"] == pytest.approx(75.0)
    # the pipeline's basic metrics pair the bands the same way
    from gpnarx.training.pipeline import basic_metrics

    b = basic_metrics(rec)
    assert b["coverage"] == pytest.approx(m["coverage"]) and b["coverage_latent"] == pytest.approx(75.0)
    html_text = rp.write_report(tmp_path / "r", "r", {}, [dict(rec, roles=["lags", "verify"])])["html"].read_text()
    assert "coverage latent [%]" in html_text and ">lag-selection<" in html_text


@pytest.mark.parametrize("roles,use", [(["train", "verify"], "training"), (["lags", "verify"], "lag-selection"),
                                       (["healthy"], "calibration"), (["validate"], "held-out"),
                                       (["verify"], "held-out"), (["damaged"], "held-out"), (None, None)])
def test_record_use_from_config_roles(roles, use):
    assert rmet.record_use(roles) == use


def test_use_note_names_the_configs_own_trained_checks_not_bouc_wens(tmp_path):
    """The note under the per-record table says which of this report's scored records trained the model,
    from the records' roles; a user's report never quotes the Bouc-Wen config's records."""
    user = [_sine_record("probe-a", roles=["verify"], role="verify"),
            _sine_record("run-b", roles=["lags", "validate"], role="validate")]
    html_text = rp.write_report(tmp_path / "u", "u", {}, user)["html"].read_text()
    assert "Bouc-Wen" not in html_text and "10/80 N" not in html_text
    both = [_sine_record("sweep-10N", roles=["train", "verify"], role="verify"),
            _sine_record("sweep-80N", roles=["train", "verify"], role="verify"),
            _sine_record("run-b", roles=["validate"], role="validate")]
    html_text = rp.write_report(tmp_path / "b", "b", {}, both)["html"].read_text()
    assert "Bouc-Wen" not in html_text
    assert "sweep-10N and sweep-80N (verify) are training records" in html_text, html_text
