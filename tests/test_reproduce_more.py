"""The real rig's quick protocols of tests/test_reproduce.py (``gpnarx reproduce bert-real --quick`` and
``bert-real-paper --quick``), in a module of their own so that pytest-xdist's loadscope runs them on one
worker while the other runs the rest of test_reproduce.py. Same checks, the helpers of test_reproduce."""
import json
from pathlib import Path

import pytest
from test_reproduce import BERT_DATA, _check_lag_choice, _check_uses, _run

from gpnarx.cli.main import main


@pytest.mark.skipif(not (BERT_DATA / "Sine").is_dir(), reason=f"real BERT records not found at {BERT_DATA}")
def test_reproduce_bert_real_quick(tmp_path, capsys):
    res = _run("bert-real", tmp_path, True, capsys)
    held_out = {k for k, v in res["records"].items() if v["role"] == "validate"}
    assert held_out == {"heldout-05Hz", "heldout-06p75Hz", "heldout-08p5Hz", "heldout-09p75Hz", "heldout-20Hz",
                        "heldout-sweep-0p10V", "heldout-noise-0p10V"}
    assert not any(k.startswith("train-") for k in res["records"])  # training records are not scored as held out
    # lags chosen by the worst record: the chosen fit is the lowest of the chosen cell's per-record fits
    surf = json.loads((tmp_path / "lag_surface.json").read_text())
    chosen = surf["chosen"]
    assert surf["criterion"] == "worst" and chosen["fit"] == pytest.approx(min(chosen["fits"].values()))
    best_worst = max(min(c["fits"].values()) for c in surf["cells"] if c["fits"])
    assert chosen["fit"] == pytest.approx(best_worst)
    # the noise calibration ran on the 'lags' records (and never lowers ML-II's value)
    nc = json.loads((Path(res["bundle"]) / "manifest.json").read_text())["noise_calibration"]
    assert nc["method"] == "heldout_ml" and nc["n_records"] == 4 and nc["n_residuals"] > 0
    # the table scores every record of the data folder, with its role, both methods and both ARX baselines
    table = json.loads((tmp_path / "summary.json").read_text())["real_table"]
    from studies.real_table import find_records

    assert set(table["records"]) == {p.name for p in find_records(BERT_DATA)}
    roles = {k: v["role"] for k, v in table["records"].items()}
    assert roles["Sine_19Hz"] == "train" and roles["Sine_06Hz"] == "lags" and roles["Sine_20Hz"] == "validate"
    assert (roles["Chirp0p20"], roles["Chirp0p05"], roles["Chirp0p10"]) == ("train", "lags", "validate")
    assert (roles["Rand0p25"], roles["Rand0p10"]) == ("train", "validate")
    classes = {k: v["class"] for k, v in table["records"].items()}
    assert classes["Sine_19Hz"] == classes["Sine_20Hz"] == "sine near resonance"
    assert classes["Sine_05Hz"] == "sine away from resonance" and classes["Chirp0p10"] == "sweep"
    assert classes["Rand0p10"] == "noise"
    row = table["records"]["Rand0p10"]
    for key in ("whole_linear", "whole_mc", "arx_search", "arx_class"):
        assert row[key]["fit"] is not None, key
    # the class ARX is fitted on every other noise run of the data folder, never on the run it scores
    others = sorted(n for n, c in classes.items() if c == "noise" and n != "Rand0p10")
    assert "Rand0p25" in others and sorted(row["arx_class"]["trained_on"]) == others
    assert row["whole_linear"]["sharpness"] > 0
    assert table["arx_search"]["criterion"] == "worst" and len(table["arx_search"]["cells"]) == 4
    checks = res["real_table_checks"]
    assert checks["n_records"] == len(table["records"]) and set(checks["methods"]) == {"whole_linear", "whole_mc"}
    # the results page is rendered from the run's JSON: re-rendering from the run folder gives the same page
    page = (tmp_path / "results-bert-real.md").read_text()
    assert "| Sine_20Hz | sine near resonance | validate |" in page and "## Lag surface" in page
    # the k-step fit table on every record, and the record with 0.5 s cut out of its middle, with its figure
    ks = table["records"]["Rand0p10"]["k_step"]
    assert table["kstep_horizons"] == [1, 8, 64, 512] and ks["1"]["fit"] > ks["free_run"]["fit"]
    gap = table["gap_record"]
    assert gap["record"] == "Sine_20Hz" and gap["nan_through_gap"] and gap["gap_seconds"] == pytest.approx(0.5)
    assert (tmp_path / gap["figure"]).is_file()
    assert "## Fit by prediction horizon (k-step-ahead)" in page and "## A record with a gap" in page
    assert main(["reproduce", "bert-real", "--out", str(tmp_path), "--from-run", "--docs",
                 str(tmp_path / "again.md")]) == 0
    assert (tmp_path / "again.md").read_text() == page
    # the band's discrepancy term was calibrated on the 'lags' records
    bd = json.loads((Path(res["bundle"]) / "manifest.json").read_text())["band_discrepancy"]
    assert bd["records"] == ["lags-06Hz", "lags-09Hz", "lags-noise-7to16s", "lags-sweep-0p05V"] and bd["scale"] >= 0
    # --table-only re-scores the run's own bundle with other paths and re-renders the page, training nothing
    capsys.readouterr()
    assert main(["--json", "reproduce", "bert-real", "--out", str(tmp_path), "--table-only", "--table-mc", "3",
                 "--docs", str(tmp_path / "mc.md")]) == 0
    again = json.loads((tmp_path / "summary.json").read_text())
    assert again["bundle"] == res["bundle"] and again["real_table"]["mc_paths"] == 3
    assert again["real_table"]["records"]["Sine_20Hz"]["whole_mc"]["fit"] is not None
    # with the run's own ARX lag search (its grid and rule), not one at the GP's lags only
    kept = ("criterion", "ny", "nu", "fit")
    assert {k: again["real_table"]["arx_search"][k] for k in kept} == {k: table["arx_search"][k] for k in kept}
    assert len(again["real_table"]["arx_search"]["cells"]) == len(table["arx_search"]["cells"]) == 4
    assert "Monte Carlo paths of the table: 3." in (tmp_path / "mc.md").read_text()


@pytest.mark.skipif(not (BERT_DATA / "Chirp").is_dir(), reason=f"real BERT sweeps not found at {BERT_DATA}")
def test_reproduce_bert_real_paper_quick(tmp_path, capsys):
    """The paper's section 4 protocol on the real sweeps, quick mode: trained on the 0.05 and 0.20 V sweeps,
    lags judged on the 0.10 V sweep, the three sweeps verified and the other records held out with their
    roles, and the receptance FRFs of the sweeps (Fig. 12(a)) from their LMS exports, softening with level."""
    res = _run("bert-real-paper", tmp_path, True, capsys)
    assert set(res["records"]) == {"sweep-0.05V", "sweep-0.20V", "sweep-0.10V", "sine-19Hz-0to16s",
                                   "sine-09Hz-0to16s", "noise-0.25V"}
    _check_uses(res["records"], {"sweep-0.05V", "sweep-0.20V"}, {"sweep-0.10V"})
    assert {res["records"][n]["role"] for n in ("sweep-0.05V", "sweep-0.20V", "sweep-0.10V")} == {"verify"}
    surf = _check_lag_choice(tmp_path, res)
    assert {k for c in surf["cells"] for k in c["fits"]} == {"sweep-0.10V"}
    assert res["paper_lags"] == {"ny": 16, "nu": 10, "fit": 96.1}
    summary = json.loads((tmp_path / "summary.json").read_text())
    rec = summary["receptance"]
    assert [r["name"] for r in rec["runs"]] == ["Chirp0p05", "Chirp0p10", "Chirp0p20"]  # by drive level
    peaks = [r["peak"] for r in rec["runs"]]
    assert peaks[0] > peaks[1] > peaks[2]  # the receptance peak falls as the drive grows
    assert all(17.0 < r["peak_freq"] < 20.0 for r in rec["runs"])
    assert (tmp_path / "receptance.png").stat().st_size > 1000
    page = (tmp_path / "results-bert-real-paper.md").read_text()
    assert "## Receptance of the sweeps (Fig. 12(a))" in page and "| Chirp0p20 |" in page
    assert main(["reproduce", "bert-real-paper", "--out", str(tmp_path), "--from-run", "--docs",
                 str(tmp_path / "again.md")]) == 0
    assert (tmp_path / "again.md").read_text() == page
