"""The training report's residual tests (training.report_residuals, training.report): every verify and validate
record gets its one-step residual tests, as numbers in report.json, a table on the page and a figure where
matplotlib is installed; the other roles get none; the pipeline attaches them."""
from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
from test_residual_tests import _arx

from gpnarx.training import report as rp
from gpnarx.training.report_residuals import RESIDUAL_ROLES, attach_residual_tests

FS = 100.0


@pytest.fixture(scope="module")
def model():
    from gpnarx.model.estimator import GPNARX

    u, y = _arx(1500, 1)
    return GPNARX(ny=2, nu=2, max_train_points=300, n_restarts=0).fit([(u, y)])


def _records():
    u, y = _arx(800, 7)
    us, ys = _arx(40, 8)  # too short for 25 lags
    base = {"fs": FS, "units": {"u": "N", "y": "m"}}

    def rec(name, role, u, y):
        return {**base, "name": name, "role": role, "u": u, "y": y, "mean": y, "lower": y - 0.1, "upper": y + 0.1}

    return [rec("fresh", "validate", u, y), rec("fresh", "verify", u, y), rec("fresh", "lags", u, y),
            rec("short", "validate", us, ys), rec("healthy-1", "healthy", u, y)]


def test_attach_only_to_verify_and_validate(model):
    assert RESIDUAL_ROLES == ("verify", "validate")
    recs = attach_residual_tests(model, _records())
    by = {(r["name"], r["role"]): r.get("residual_tests") for r in recs}
    assert by[("fresh", "lags")] is None and by[("healthy-1", "healthy")] is None
    check = by[("fresh", "validate")]
    assert by[("fresh", "verify")] is check  # one record under two roles: predicted once
    assert check["n"] == 798 and check["fit"] > 95 and "coverage" not in check  # the mean only
    assert check["residual_tests"]["passed"] is True and check["residual_tests"]["lags"] == 25
    assert "more than 50 residuals" in by[("short", "validate")]["error"]


def test_report_holds_the_numbers_table_and_figures(model, tmp_path):
    recs = attach_residual_tests(model, _records())
    paths = rp.write_report(tmp_path / "rep", "residuals", {}, recs)
    rep = json.loads(paths["json"].read_text())
    entries = {(r["name"], r["role"]): r for r in rep["records"]}
    t = entries[("fresh", "validate")]["residual_tests"]["residual_tests"]
    assert len(t["autocorrelation"]["r"]) == 25 and len(t["cross_correlation"]["r"]) == 51
    assert t["autocorrelation"]["ljung_box"]["df"] == 25 and 0 <= t["autocorrelation"]["outside_share"] <= 1
    assert "residual_tests" not in entries[("fresh", "lags")]
    assert entries[("short", "validate")]["residual_tests"]["error"]
    assert "residual_figure" not in entries[("short", "validate")]
    figs = {entries[k]["residual_figure"] for k in (("fresh", "validate"), ("fresh", "verify"))}
    assert figs == {"residuals_fresh.png", "residuals_fresh_2.png"}
    assert paths["residuals"]["fresh"].name in figs  # keyed by name, as paths["records"]
    for fn in figs:
        assert (tmp_path / "rep" / fn).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page = paths["html"].read_text()
    section = page[page.index("<h2>Residual tests</h2>"):page.index("<h2>Figures</h2>")]
    assert "Ljung-Box p" in section and "not tested: the residual tests at 25 lags" in section
    assert section.count("<tr>") == 1 + 3  # header, fresh twice, short
    srcs = dict((fn, src) for src, fn in re.findall(r"<img src='([^']*)' data-file='([^']*)'", section))
    assert set(srcs) == figs
    for fn, src in srcs.items():
        assert src == "data:image/png;base64," + base64.b64encode((tmp_path / "rep" / fn).read_bytes()).decode()


def test_without_matplotlib_the_numbers_stay(model, tmp_path, monkeypatch):
    monkeypatch.setattr(rp, "record_figure", None)
    monkeypatch.setattr(rp, "residual_figure", None)
    paths = rp.write_report(tmp_path / "rep", "residuals", {}, attach_residual_tests(model, _records()))
    rep = json.loads(paths["json"].read_text())
    assert rep["records"][0]["residual_tests"]["residual_tests"]["passed"] is True
    assert "residuals" not in paths and not list((tmp_path / "rep").glob("*.png"))
    assert "<h2>Residual tests</h2>" in paths["html"].read_text()


def test_a_report_without_tested_records_has_no_section(tmp_path):
    from test_report import _sine_record

    paths = rp.write_report(tmp_path / "rep", "plain", {}, [_sine_record()])
    assert "Residual tests" not in paths["html"].read_text()
    assert "residual_tests" not in json.loads(paths["json"].read_text())["records"][0]


def test_the_pipeline_reports_its_verify_record(tmp_path):
    from test_pipeline import SMALL_CONFIG

    from gpnarx.training.pipeline import train

    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG.format(ny=4, nu=4))
    res = train(cfg, tmp_path / "reg", mc_paths=8, report_method="linear")
    rep = json.loads((tmp_path / "reg" / "bw-small" / res["version"] / "report" / "report.json").read_text())
    tested = {(r["name"], r["role"]): r for r in rep["records"] if r.get("residual_tests")}
    assert list(tested) == [("lag-sweep", "verify")]  # its 'lags' role and the healthy records: none
    r = tested[("lag-sweep", "verify")]
    assert r["residual_tests"]["n"] == 750 - 4 and np.isfinite(r["residual_tests"]["fit"])
    # the record's second entry (after its 'lags' one): its figures' names carry _2
    assert (r["figure"], r["residual_figure"]) == ("record_lag-sweep_2.png", "residuals_lag-sweep_2.png")
