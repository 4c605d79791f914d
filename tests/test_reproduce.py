"""Paper protocols end to end (issue 8). Quick modes run in the default suite; the full
protocols are marked slow (python -m pytest -m slow)."""
import json
from pathlib import Path

import numpy as np
import pytest

from gpnarx.cli.main import main

BERT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "bert-t5nm"


def _run(system, out, quick, capsys):
    argv = ["reproduce", system, "--out", str(out), "--json"] + (["--quick"] if quick else [])
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_reproduce_bouc_wen_quick(tmp_path, capsys):
    res = _run("bouc-wen", tmp_path, True, capsys)
    assert res["quick"] is True and res["paper_lags"] == {"ny": 20, "nu": 17, "fit": 92.4}
    assert res["chosen_lags"]["ny"] in (2, 4) and res["chosen_lags"]["nu"] in (2, 4)
    expected = {"sweep-10N", "sweep-50N", "sweep-80N", "sine-10N", "sine-50N", "sine-80N",
                "multisine-10N", "multisine-50N", "multisine-80N"}
    assert set(res["records"]) == expected
    summary = json.loads((tmp_path / "summary.json").read_text())
    base = summary["baselines"]
    assert set(base) == expected and all("linear ARX" in v for v in base.values())
    report = Path(res["bundle"]) / "report"
    rj = json.loads((report / "report.json").read_text())
    assert rj["lag_surface"] and rj["paper"]["lags"]["fit"] == 92.4
    # the summary and the report say whether the best cell sits on the grid's largest ny / nu
    from gpnarx.training.lags import grid_edge

    surf = json.loads((tmp_path / "lag_surface.json").read_text())
    assert summary["lag_grid_edge"] == grid_edge(surf["best"], surf["ny"], surf["nu"]) == rj["lag_surface"]["edge"]
    html = (report / "report.html").read_text()
    assert "linear ARX" in html and "sine-50N" in html
    assert (tmp_path / "lag_surface.png").is_file()
    assert res["wall_seconds"] < 120


@pytest.mark.skipif(not (BERT_DATA / "Sine").is_dir(), reason=f"real BERT records not found at {BERT_DATA}")
def test_reproduce_bert_real_quick(tmp_path, capsys):
    res = _run("bert-real", tmp_path, True, capsys)
    held_out = {k for k, v in res["records"].items() if v["role"] == "validate"}
    assert held_out == {"heldout-05Hz", "heldout-06p75Hz", "heldout-08p5Hz", "heldout-09p75Hz", "heldout-20Hz"}
    assert not any(k.startswith("train-") for k in res["records"])  # training records are not scored as held out
    # lags chosen by the worst record: the chosen fit is the lowest of the chosen cell's per-record fits
    surf = json.loads((tmp_path / "lag_surface.json").read_text())
    chosen = surf["chosen"]
    assert surf["criterion"] == "worst" and chosen["fit"] == pytest.approx(min(chosen["fits"].values()))
    best_worst = max(min(c["fits"].values()) for c in surf["cells"] if c["fits"])
    assert chosen["fit"] == pytest.approx(best_worst)
    # the noise calibration ran on the 'lags' records (and never lowers ML-II's value)
    nc = json.loads((Path(res["bundle"]) / "manifest.json").read_text())["noise_calibration"]
    assert nc["method"] == "heldout_ml" and nc["n_records"] == 3 and nc["n_residuals"] > 0
    # the table scores every record of the data folder, with its role, both methods and both ARX baselines
    table = json.loads((tmp_path / "summary.json").read_text())["real_table"]
    from gpnarx.training.real_table import find_records

    assert set(table["records"]) == {p.name for p in find_records(BERT_DATA)}
    roles = {k: v["role"] for k, v in table["records"].items()}
    assert roles["Sine_19Hz"] == "train" and roles["Sine_06Hz"] == "lags" and roles["Sine_20Hz"] == "validate"
    row = table["records"]["Sine_09p75Hz"]
    for key in ("whole_linear", "whole_mc", "window_linear", "window_mc", "whole_arx_8_4", "window_arx_8_4"):
        assert row[key]["fit"] is not None, key
    assert res["real_table_checks"]["n_records"] == len(table["records"])
    # the results page is rendered from the run's JSON: re-rendering from the run folder gives the same page
    page = (tmp_path / "results-bert-real.md").read_text()
    assert "| Sine_20Hz | validate |" in page and "## Lag surface" in page
    assert main(["reproduce", "bert-real", "--out", str(tmp_path), "--from-run", "--docs",
                 str(tmp_path / "again.md")]) == 0
    assert (tmp_path / "again.md").read_text() == page


@pytest.fixture(scope="module")
def bouc_wen_full(tmp_path_factory):
    out = tmp_path_factory.mktemp("bw-full")
    argv = ["reproduce", "bouc-wen", "--out", str(out), "--json"]
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return json.loads(buf.getvalue())


@pytest.mark.slow
def test_reproduce_bouc_wen_full_meets_targets(bouc_wen_full):
    res = bouc_wen_full
    assert res["chosen_lags"]["fit"] >= 92.4 - 3
    for name in ("sweep-50N", "sweep-80N"):
        assert res["records"][name]["fit_clean"] >= 90, name
    for name, rec in res["records"].items():
        if rec["role"] == "validate":
            assert rec["coverage_clean"] >= 95, name
    assert res["wall_seconds"] < 15 * 60


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known miss: the 10 N sweep's clean fit is 79.6 % at the chosen lags "
                   "(target 90 %; 88.1-90.4 % at the paper's 20/17 over 11 training-noise draws), see "
                   "docs/results-bouc-wen.md")
def test_reproduce_bouc_wen_full_10n_sweep_fit(bouc_wen_full):
    assert bouc_wen_full["records"]["sweep-10N"]["fit_clean"] >= 90


def test_reproduce_bert_standin_quick_runs_the_monitor_and_novelty_study(tmp_path, capsys):
    res = _run("bert-standin", tmp_path, True, capsys)
    assert {"sweep-0.10V", "sweep-0.15V", "sine-18Hz-0.15V", "noise-0.30V"} == set(res["records"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    oracle = summary["oracle"]  # nominal stand-in vs each seeded realization: the scatter-only ceiling
    assert set(oracle) == set(res["records"]) and all(np.isfinite(v["fit_clean"]) for v in oracle.values())
    assert oracle["sine-18Hz-0.15V"]["fit_clean"] > oracle["noise-0.30V"]["fit_clean"]
    mon = summary["monitor"]
    assert Path(mon["bundle"]).name == "1" and Path(mon["bundle"]).parent.name == "bert-standin-monitor"
    roles = {v["role"] for v in mon["records"].values()}
    assert {"healthy", "damaged", "validate"} <= roles
    assert mon["novelty"]["threshold"] > 0 and mon["novelty"]["n_healthy"] == 6
    nov = summary["novelty"]
    assert nov["probe"] == {"excitation": "sine", "amplitude": 0.15, "freq": 9.0}
    for far in ("0.01", "0.05"):
        rates = nov["rates"][far]
        assert set(rates) == {"healthy 5 N m (unseen)", "7 N m", "9 N m", "4 N m (partly loosened)"}
        assert all(0.0 <= r <= 1.0 for r in rates.values())
    assert (tmp_path / "novelty_roc.png").stat().st_size > 1000


def test_standin_oracle_uses_each_records_own_input():
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config
    from gpnarx.training.reproduce import standin_oracle

    names = {"noise-0.30V": None, "sine-18Hz-0.15V": None}
    first = standin_oracle(load_config(shipped_config("bert-standin")), names)
    again = standin_oracle(load_config(shipped_config("bert-standin")), names)
    assert first == again  # the noise record's excitation is not redrawn
    assert first["sine-18Hz-0.15V"]["fit_clean"] > 90  # nominal vs one realization of a steady sine
