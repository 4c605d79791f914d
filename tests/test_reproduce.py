"""Paper protocols end to end (issues 8 and 22). Quick modes run in the default suite and check the
same code (lag choice, roles, both coverages, novelty thresholds and rates) on tiny runs; the full
protocols are marked slow (python -m pytest -m slow): each target of issue 8 is one test, and a
target still missed is a strict xfail whose reason quotes the figure the full run reached.

GPNARX_SLOW_OUT=DIR keeps the full runs' folders under DIR/SYSTEM (summary.json, lag_surface.json,
the bundle and its report), e.g. to render docs/results-*.md from them with ``gpnarx reproduce
SYSTEM --out DIR/SYSTEM --from-run --docs ...``.
"""
import contextlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.special import ndtri

from gpnarx.cli.main import main
from gpnarx.training.datapaths import bert_data_dir
from gpnarx.training.lagchoice import DEFAULT_TOLERANCE

BERT_DATA = bert_data_dir()
STANDIN_FULL_MC = 4096  # the protocol's Monte Carlo paths for the stand-in (section 4; --mc 4096)


def _run(system, out, quick, capsys):
    argv = ["reproduce", system, "--out", str(out), "--json"] + (["--quick"] if quick else [])
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def _check_lag_choice(out: Path, res: dict, tolerance: float = DEFAULT_TOLERANCE):
    """The chosen cell is the one the documented rule picks on the surface this run produced (the
    smallest ny + nu within ``tolerance`` points of the best fit; cells scored by their mean over the
    'lags' records), and the bundle was trained at it."""
    surf = json.loads((out / "lag_surface.json").read_text())
    cells = [c for c in surf["cells"] if c["fit"] is not None and np.isfinite(c["fit"])]
    assert len(cells) == len(surf["ny"]) * len(surf["nu"])
    for c in cells:  # each cell's score is the mean of its per-record fits
        assert c["fit"] == pytest.approx(np.mean(list(c["fits"].values())))
    best = max(c["fit"] for c in cells)
    near = [c for c in cells if c["fit"] >= best - tolerance]
    rank = min(c["ny"] + c["nu"] for c in near)
    expect = max((c for c in near if c["ny"] + c["nu"] == rank), key=lambda c: c["fit"])
    chosen = surf["chosen"]
    assert (chosen["ny"], chosen["nu"]) == (expect["ny"], expect["nu"]) and chosen["fit"] == expect["fit"]
    assert res["chosen_lags"] == {"ny": chosen["ny"], "nu": chosen["nu"], "fit": pytest.approx(chosen["fit"])}
    manifest = json.loads((Path(res["bundle"]) / "manifest.json").read_text())
    assert manifest["lags"] == {"ny": chosen["ny"], "nu": chosen["nu"]}
    return surf


def _check_uses(records: dict, training: set, lag_selection: set):
    for name, rec in records.items():
        want = "training" if name in training else "lag-selection" if name in lag_selection else "held-out"
        assert rec["use"] == want, (name, rec["use"], want)


def _md_table(page: str, first_header: str) -> list[dict]:
    """The rows of the first Markdown table of ``page`` whose header starts with ``first_header``."""
    lines = page.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"| {first_header}"))
    cells = lambda ln: [c.strip() for c in ln.strip().strip("|").split("|")]  # noqa: E731
    head = cells(lines[start])
    rows = []
    for ln in lines[start + 2:]:
        if not ln.startswith("|"):
            break
        rows.append(dict(zip(head, cells(ln))))
    return rows


def _check_page_numbers(out: Path, summary: dict, clean: bool):
    """The results page the run wrote (OUT/results-SYSTEM.md) holds the run's JSON figures: every number of
    the records table equals the summary's value to its printed precision; --from-run renders the same page."""
    system = summary["system"]
    page = (out / f"results-{system}.md").read_text()
    rows = {r["record"]: r for r in _md_table(page, "record | use |")}
    assert set(rows) == set(summary["records"])
    cols = {"fit %": "fit", "coverage %": "coverage"} | (
        {"fit clean %": "fit_clean", "coverage latent %": "coverage_latent"} if clean else {})
    uses = {"training": "training", "lag selection": "lag-selection", "held out": "held-out"}
    for name, row in rows.items():
        rec = summary["records"][name]
        assert uses[row["use"]] == rec["use"], name
        for col, key in cols.items():
            assert abs(float(row[col]) - rec[key]) <= 0.05 + 1e-9, (name, col, row[col], rec[key])
        bw = next(v for k, v in row.items() if k.startswith("band width"))
        assert float(bw) == pytest.approx(rec["band_width"], rel=5e-3), name
    ch = summary["chosen_lags"]
    assert f"chosen lags ny={ch['ny']}, nu={ch['nu']} (lag-surface fit {ch['fit']:.1f} %)" in page
    again = out / "again.md"
    assert main(["reproduce", system, "--out", str(out), "--from-run", "--docs", str(again)]) == 0
    assert again.read_text() == page
    return page


def _check_novelty_study(nov: dict):
    """Thresholds are the configured quantile of the log-normal fit to the calibration scores (never
    below their largest when there are fewer than 1/rate of them), and each rate is the share of that
    class's scores above it."""
    calib = np.asarray(nov["calibration_scores"], float)
    logs = np.log(calib)
    for far, thr in nov["thresholds"].items():
        expect = float(np.exp(logs.mean() + ndtri(1 - float(far)) * logs.std(ddof=1)))
        if calib.size < 1 / float(far):
            expect = max(expect, float(calib.max()))
        assert thr == pytest.approx(expect, rel=1e-9), far
        for cls, rate in nov["rates"][far].items():
            assert rate == pytest.approx(np.mean(np.asarray(nov["scores"][cls]) > thr)), (far, cls)


def test_reproduce_bouc_wen_quick(tmp_path, capsys):
    res = _run("bouc-wen", tmp_path, True, capsys)
    assert res["quick"] is True and res["paper_lags"] == {"ny": 20, "nu": 17, "fit": 92.4}
    _check_lag_choice(tmp_path, res)
    _check_uses(res["records"], {"sweep-10N", "sweep-80N"}, {"sweep-50N"})
    for name, rec in res["records"].items():  # both coverages on every simulated record
        assert 0 <= rec["coverage"] <= 100 and 0 <= rec["coverage_latent"] <= 100, name
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
    assert "coverage latent [%]" in html and ">lag-selection<" in html and ">held-out<" in html
    m = next(r["metrics"] for r in rj["records"] if r["name"] == "sine-10N")
    assert "coverage_clean" not in m and m["use"] == "held-out"
    assert (m["coverage"], m["coverage_latent"]) == (res["records"]["sine-10N"]["coverage"],
                                                   res["records"]["sine-10N"]["coverage_latent"])
    _check_page_numbers(tmp_path, summary, clean=True)
    assert (tmp_path / "lag_surface.png").is_file()
    assert res["wall_seconds"] > 0  # the run's wall time (summary.json): a figure, not a limit of a unit test


def test_docs_real_paper_page_is_the_render_of_its_stored_run():
    """docs/results-bert-real-paper.md is what results_page renders from docs/runs/bert-real-paper, a full
    (not quick) run with the protocol's 4096 paths, and its receptance figure is stored beside the run."""
    from gpnarx.training.reproduce import results_page

    docs = Path(__file__).resolve().parents[1] / "docs"
    run = docs / "runs" / "bert-real-paper"
    summary = json.loads((run / "summary.json").read_text())
    surface = json.loads((run / "lag_surface.json").read_text())
    assert summary["system"] == "bert-real-paper" and not summary["quick"] and summary["mc_paths"] == 4096
    assert (docs / "results-bert-real-paper.md").read_text() == results_page(summary, surface)
    assert (run / "receptance.png").stat().st_size > 1000
    # the stored figures are a working model's: no record's Monte Carlo mean below the linear ARX fitted on the
    # same training records (a run whose paths diverged scores far below it), and the run's lags are the config's
    for name, rec in summary["records"].items():
        assert rec["fit"] >= summary["baselines"][name]["linear ARX"]["fit"], name
    assert summary["config_lags"] == {k: summary["chosen_lags"][k] for k in ("ny", "nu")}


def _full(tmp_path_factory, system, *extra):
    """One full protocol run (CLI, --json); returns its answer, summary and folder."""
    keep = os.environ.get("GPNARX_SLOW_OUT")
    out = Path(keep) / system if keep else tmp_path_factory.mktemp(system)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["reproduce", system, "--out", str(out), "--json", *extra]) == 0
    res = json.loads(buf.getvalue())
    return {"res": res, "summary": json.loads((out / "summary.json").read_text()), "out": out,
            "report": json.loads((Path(res["bundle"]) / "report" / "report.json").read_text())}


def _report_metrics(run, name):
    return next(r["metrics"] for r in run["report"]["records"] if r["name"] == name)


# ---------------------------------------------------------------------------------------- Bouc-Wen, full
@pytest.fixture(scope="module")
def bouc_wen_full(tmp_path_factory):
    return _full(tmp_path_factory, "bouc-wen")


@pytest.mark.slow
def test_bouc_wen_full_lags_within_3_points_of_the_paper_and_under_15_minutes(bouc_wen_full):
    res = bouc_wen_full["res"]
    _check_lag_choice(bouc_wen_full["out"], res)
    _check_uses(res["records"], {"sweep-10N", "sweep-80N"}, {"sweep-50N"})
    assert res["chosen_lags"]["fit"] >= 92.4 - 3
    assert res["wall_seconds"] < 15 * 60


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sweep-50N", "sweep-80N"])
def test_bouc_wen_full_verification_fit_at_least_90(bouc_wen_full, name):
    # 80 N is a training record (use 'training'), 50 N the lag-selection record: neither is held out
    assert bouc_wen_full["res"]["records"][name]["fit_clean"] >= 90


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known miss: the 10 N sweep's clean fit is 79.6 % at the chosen lags "
                   "(target 90 %; 88.1-90.4 % at the paper's 20/17 over 11 training-noise draws), see "
                   "docs/study-bouc-wen-10n.md")
def test_reproduce_bouc_wen_full_10n_sweep_fit(bouc_wen_full):
    assert bouc_wen_full["res"]["records"]["sweep-10N"]["fit_clean"] >= 90


BW_VALIDATE = ["sine-10N", "sine-50N", "sine-80N", "multisine-10N", "multisine-50N", "multisine-80N"]


@pytest.mark.slow
@pytest.mark.parametrize("name", BW_VALIDATE)
def test_bouc_wen_full_predictive_band_covers_95_percent_of_the_measured_output(bouc_wen_full, name):
    rec = bouc_wen_full["res"]["records"][name]
    assert rec["use"] == "held-out" and rec["coverage"] >= 95


def _latent_miss(name, figure):
    return pytest.param(name, marks=pytest.mark.xfail(strict=True, reason=(
        f"known miss: the latent 99 % band (no noise term) covers {figure} % of the {name} noise-free output "
        "(target 95 %; the predictive band covers the measured output above 95 %): the band holds the model's "
        "uncertainty, not its bias on the broadband multisines (fit clean 76.5 / 80.2 % at 50 / 80 N)")))


@pytest.mark.slow
@pytest.mark.parametrize("name", BW_VALIDATE[:4] + [_latent_miss("multisine-50N", 94.8),
                                                    _latent_miss("multisine-80N", 89.7)])
def test_bouc_wen_full_latent_band_covers_95_percent_of_the_noise_free_output(bouc_wen_full, name):
    assert bouc_wen_full["res"]["records"][name]["coverage_latent"] >= 95


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sweep-10N", "sweep-50N", "sweep-80N"])
def test_bouc_wen_full_predicted_psd_peak_within_1_hz(bouc_wen_full, name):
    m = _report_metrics(bouc_wen_full, name)
    assert abs(m["psd_peaks_predicted"][0] - m["psd_peaks_measured"][0]) <= 1.0


# ------------------------------------------------------------------------------------- stand-in, full
@pytest.fixture(scope="module")
def standin_full(tmp_path_factory):
    return _full(tmp_path_factory, "bert-standin", "--mc", str(STANDIN_FULL_MC))


@pytest.mark.slow
def test_standin_full_chosen_lags_fit_at_least_90_on_the_010V_sweep(standin_full):
    res = standin_full["res"]
    _check_lag_choice(standin_full["out"], res)
    _check_uses(res["records"], set(), {"sweep-0.10V"})
    assert res["mc_paths"] == STANDIN_FULL_MC
    assert res["chosen_lags"]["fit"] >= 90 and res["records"]["sweep-0.10V"]["fit"] >= 90


@pytest.mark.slow
def test_standin_full_predictive_band_covers_95_percent_of_the_unseen_015V_sweep(standin_full):
    rec = standin_full["res"]["records"]["sweep-0.15V"]
    assert rec["use"] == "held-out" and rec["coverage"] >= 95


@pytest.mark.slow
def test_standin_full_latent_band_covers_95_percent_of_the_unseen_015V_sweep_noise_free(standin_full):
    assert standin_full["res"]["records"]["sweep-0.15V"]["coverage_latent"] >= 95


@pytest.mark.slow
def test_standin_full_detects_9Nm_at_least_95_percent_at_1_percent_false_alarms(standin_full):
    nov = standin_full["summary"]["novelty"]
    assert nov["n_per_class"] == 20 and nov["mc_paths"] == 0
    _check_novelty_study(nov)
    assert nov["rates"]["0.01"]["9 N m"] >= 0.95


# ------------------------------------------------------------------------------------ real BERT, full
@pytest.fixture(scope="module")
def bert_real_full(tmp_path_factory):
    if not (BERT_DATA / "Sine").is_dir():
        pytest.skip(f"real BERT records not found at {BERT_DATA}")
    return _full(tmp_path_factory, "bert-real", "--table-mc", "0")


REAL_HELDOUT = ["heldout-05Hz", "heldout-06p75Hz", "heldout-08p5Hz", "heldout-09p75Hz", "heldout-20Hz",
                "heldout-sweep-0p10V"]


@pytest.mark.slow
@pytest.mark.parametrize("name", REAL_HELDOUT)
def test_bert_real_full_heldout_fit_at_least_the_linear_arx(bert_real_full, name):
    rec = bert_real_full["res"]["records"][name]
    arx = bert_real_full["summary"]["baselines"][name]["linear ARX"]["fit"]
    assert rec["use"] == "held-out" and rec["fit"] >= arx


@pytest.mark.slow
@pytest.mark.parametrize("name", REAL_HELDOUT)
def test_bert_real_full_heldout_coverage_at_least_90(bert_real_full, name):
    assert bert_real_full["res"]["records"][name]["coverage"] >= 90


@pytest.mark.slow
def test_bert_real_full_two_superharmonic_records_20_points_above_arx_with_the_2x_harmonic(bert_real_full):
    good = []
    for name in ("heldout-06p75Hz", "heldout-08p5Hz", "heldout-09p75Hz"):
        m = _report_metrics(bert_real_full, name)
        gain = m["fit"] - bert_real_full["summary"]["baselines"][name]["linear ARX"]["fit"]
        h2 = abs(m["harmonics_db_predicted"][1] - m["harmonics_db_measured"][1])
        if gain >= 20 and h2 <= 6:
            good.append(name)
    assert len(good) >= 2, good


@pytest.mark.slow
def test_bert_real_full_every_record_whole_from_rest_without_divergence(bert_real_full):
    checks = bert_real_full["summary"]["real_table"]["checks"]
    assert checks["diverged"] == [] and checks["n_records"] >= 14


def test_reproduce_bert_standin_quick_runs_the_monitor_and_novelty_study(tmp_path, capsys):
    res = _run("bert-standin", tmp_path, True, capsys)
    assert {"sweep-0.10V", "sweep-0.15V", "sine-18Hz-0.15V", "noise-0.30V"} == set(res["records"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    oracle = summary["oracle"]  # nominal stand-in vs each seeded realization: the scatter-only ceiling
    assert set(oracle) == set(res["records"]) and all(np.isfinite(v["fit_clean"]) for v in oracle.values())
    assert oracle["sine-18Hz-0.15V"]["fit_clean"] > oracle["noise-0.30V"]["fit_clean"]
    _check_lag_choice(tmp_path, res)
    _check_uses(res["records"], set(), {"sweep-0.10V"})
    mon = summary["monitor"]
    assert Path(mon["bundle"]).name == "1" and Path(mon["bundle"]).parent.name == "bert-standin-monitor"
    roles = {v["role"] for v in mon["records"].values()}
    assert {"healthy", "damaged", "validate"} <= roles
    assert {v["use"] for v in mon["records"].values() if v["role"] == "healthy"} == {"calibration"}
    # the monitor's threshold: the configured quantile of the log-normal fit to its healthy records' scores
    nv = mon["novelty"]
    healthy = [v["novelty_score"] for v in mon["records"].values() if v["role"] == "healthy"]
    assert nv["n_healthy"] == 6 and sorted(nv["healthy_scores"]) == pytest.approx(sorted(healthy))
    _check_novelty_study({"calibration_scores": healthy, "thresholds": {str(nv["false_alarm_rate"]): nv["threshold"]},
                          "rates": {str(nv["false_alarm_rate"]): {}}, "scores": {}})
    nov = summary["novelty"]
    assert nov["probe"] == {"excitation": "sine", "amplitude": 0.15, "freq": 9.0}
    assert set(nov["thresholds"]) == set(nov["rates"]) == {"0.01", "0.05"}
    for far in ("0.01", "0.05"):
        assert set(nov["rates"][far]) == {"healthy 5 N m (unseen)", "7 N m", "9 N m", "4 N m (partly loosened)"}
    _check_novelty_study(nov)
    page = _check_page_numbers(tmp_path, summary, clean=True)
    for far, thr in nov["thresholds"].items():  # the novelty table: thresholds and counts flagged per class
        row = next(r for r in _md_table(page, "false-alarm rate") if float(r["false-alarm rate"].rstrip(" %"))
                   == pytest.approx(100 * float(far)))
        assert float(row["threshold"]) == pytest.approx(thr, rel=5e-4)
        for cls, rate in nov["rates"][far].items():
            assert row[f"{cls} flagged"].startswith(f"{round(rate * nov['n_per_class'])} / {nov['n_per_class']} ")
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


def test_docs_real_results_page_is_the_render_of_its_stored_run():
    """docs/results-bert-real.md is what results_page renders from docs/runs/bert-real (the run's JSON,
    its table re-scored with 1024 paths by --table-only): a figure on the page cannot drift from its run."""
    from gpnarx.training.reproduce import results_page

    docs = Path(__file__).resolve().parents[1] / "docs"
    summary = json.loads((docs / "runs" / "bert-real" / "summary.json").read_text())
    surface = json.loads((docs / "runs" / "bert-real" / "lag_surface.json").read_text())
    assert summary["system"] == "bert-real" and not summary["quick"] and summary["real_table"]["mc_paths"] == 1024
    assert (docs / "results-bert-real.md").read_text() == results_page(summary, surface)
    checks = summary["real_table"]["checks"]
    from studies.real_table import find_records

    assert checks["diverged"] == [] and checks["n_records"] == len(summary["real_table"]["records"])
    if BERT_DATA.is_dir():  # the stored run covers every record of the lab data folder (not checkable without it)
        assert checks["n_records"] == len(find_records(BERT_DATA))
    # every Monte Carlo row the table holds is counted by its checks, and where they came from is on the page
    table = summary["real_table"]
    with_mc = sorted(n for n, r in table["records"].items() if "whole_mc" in r)
    assert sorted(table["mc_records"]) == with_mc and checks["methods"]["whole_mc"]["n_scored"] == len(with_mc)
    if table.get("mc_note"):
        assert table["mc_note"] in (docs / "results-bert-real.md").read_text()
    # the shipped lags are the stored surface's choice, judged with the shipped model's own settings
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config
    from gpnarx.training.reproduce import surface_settings

    shipped = load_config(shipped_config("bert-real")).model
    assert summary["config_lags"] == {k: summary["chosen_lags"][k] for k in ("ny", "nu")}
    assert summary["config_lags"] == {k: shipped[k] for k in ("ny", "nu")}
    assert {k: surface["settings"].get(k) for k in ("mode", "max_train_points")} == {"mode": None,
                                                                                    "max_train_points": None}
    assert surface["settings"] == surface_settings("bert-real")
    assert "with the config's own `[model]` settings" in (docs / "results-bert-real.md").read_text()


def test_reproduce_runs_a_study_of_the_checkout(tmp_path):
    """gpnarx reproduce STUDY -- ARGS runs studies/MODULE.py (not in the wheel) with its own arguments."""
    from gpnarx.cli.main import main

    docs = Path(__file__).resolve().parents[1] / "docs"
    out = tmp_path / "page.md"
    assert main(["reproduce", "accelerator-page", "--", str(docs / "runs" / "accelerator"), str(out)]) == 0
    assert out.read_text() == (docs / "results-accelerator.md").read_text()


def test_reproduce_says_a_study_needs_a_checkout(monkeypatch, capsys):
    """Where no studies/ folder is found (an installed wheel), the study's command is one error line, exit 1."""
    import sys

    import gpnarx.training.checkout as checkout
    from gpnarx.cli.main import main

    for name in [m for m in sys.modules if m == "studies" or m.startswith("studies.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if not (Path(p or ".").resolve() / "studies").is_dir()])
    monkeypatch.chdir(Path(__file__).resolve().parent)
    monkeypatch.setattr(checkout, "checkout_root", lambda: None)
    assert main(["reproduce", "cycle-study", "--", "--help"]) == 1
    err = capsys.readouterr().err
    assert "studies/ folder" in err and "checkout" in err and "Traceback" not in err
    with pytest.raises(checkout.CheckoutRequired):
        checkout.load_study("real_table")


def test_a_study_task_runs_in_worker_processes_started_without_the_checkout(tmp_path):
    """The `gpnarx` command has no checkout on its path: a study's function sent to joblib workers that were
    started before any study was loaded (as the lag surface's are) is named through ``call_study``, which the
    workers can unpickle; the study's function itself could not be (ModuleNotFoundError: 'studies')."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import sys
        from pathlib import Path
        from joblib import Parallel, delayed
        from gpnarx.training.checkout import call_study
        assert not any(Path(p or ".").resolve().joinpath("studies").is_dir() for p in sys.path)
        Parallel(n_jobs=2)(delayed(abs)(-i) for i in range(4))
        roles = (["lags"], [], ["validate"])
        print(Parallel(n_jobs=2)(delayed(call_study)("real_table", "role_of", r) for r in roles))
        """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "['lags', 'unseen', 'validate']"
