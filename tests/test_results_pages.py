"""The simulated systems' results pages are renders of their runs' JSON (issue 22): docs/results-SYSTEM.md
equals what training.reproduce.results_page renders from docs/runs/SYSTEM/ (the run's summary.json and
lag_surface.json), so a figure on the page cannot drift from its run. Re-render with
``gpnarx reproduce SYSTEM --out docs/runs/SYSTEM --from-run --docs docs/results-SYSTEM.md``; a new run
replaces both the JSON and the page."""
import json
from pathlib import Path

import pytest

from gpnarx.training.reproduce import results_page

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.mark.parametrize("system", ["bouc-wen", "bert-standin"])
def test_docs_results_page_is_the_render_of_its_stored_run(system):
    run = DOCS / "runs" / system
    summary = json.loads((run / "summary.json").read_text())
    surface = json.loads((run / "lag_surface.json").read_text())
    assert summary["system"] == system and not summary["quick"]
    page = (DOCS / f"results-{system}.md").read_text()
    assert page == results_page(summary, surface), f"docs/results-{system}.md differs from its run's render"
    # every record of the run is on the page, with its use and both coverages
    for name, rec in summary["records"].items():
        row = next(ln for ln in page.splitlines() if ln.startswith(f"| {name} |"))
        assert f" {rec['coverage']:.1f} " in row and f" {rec['coverage_latent']:.1f} " in row, name


def test_docs_accelerator_page_is_the_render_of_its_stored_gpu_run():
    """docs/results-accelerator.md is what studies.accelerator_page renders from docs/runs/accelerator/ (the
    GPU run of bench/bench_gpu.py and studies/rows_study.py): every figure on it comes from that run."""
    from studies.accelerator_page import render

    run = DOCS / "runs" / "accelerator"
    page = (DOCS / "results-accelerator.md").read_text()
    assert page == render(run), "docs/results-accelerator.md differs from its run's render"
    bench = [ln for ln in (run / "bench_gpu.txt").read_text().splitlines() if ln.startswith("RESULT ")]
    assert bench and all("device=gpu" in ln for ln in bench)
    rows = json.loads((run / "rows_study.json").read_text())
    for r in rows["rows"]:
        assert f"| exact, N = {r['n_train']} |" in page


def test_docs_exact_real_page_is_the_render_of_its_stored_run():
    """docs/results-bert-real-exact.md is studies.exact_study's render of docs/runs/bert-real-exact (and of the
    shipped model's stored run it is set against)."""
    from studies.exact_study import render

    summary = json.loads((DOCS / "runs" / "bert-real-exact" / "summary.json").read_text())
    shipped = json.loads((DOCS / "runs" / "bert-real-sparse" / "summary.json").read_text())
    split = json.loads((DOCS / "runs" / "bert-real-exact" / "split_study.json").read_text())
    page = (DOCS / "results-bert-real-exact.md").read_text()
    assert page == render(summary, shipped, split), "docs/results-bert-real-exact.md differs from its run's render"
    assert summary["mode"] == "exact"
    for cell in split["cells"]:  # every cell of the split study is on the page, with its worst 'lags' fit
        assert f"| {cell['noise_split']:g} | " in page and f"{cell['worst_lags_fit']:.1f}" in page
    for name, r in summary["real_table"]["records"].items():
        if r["role"] == "validate":
            assert f"| {name} | {r['whole_linear']['fit']:.1f} |" in page, name


def test_bouc_wen_page_says_which_model_its_figures_come_from():
    """The stored run chose its own lags; the page names them and the shipped config's, which differ."""
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config

    summary = json.loads((DOCS / "runs" / "bouc-wen" / "summary.json").read_text())
    page = (DOCS / "results-bouc-wen.md").read_text()
    ch, model = summary["chosen_lags"], load_config(shipped_config("bouc-wen")).model
    assert f"Model of these figures: ny={ch['ny']}, nu={ch['nu']}" in page
    if (model["ny"], model["nu"]) != (ch["ny"], ch["nu"]):
        assert f"ny={model['ny']}, nu={model['nu']}: the model `gpnarx train bouc-wen`" in page


def test_docs_benchmarks_page_is_the_render_of_its_stored_result_lines():
    """docs/benchmarks.md is gpnarx.training.pages.benchmarks's render of the RESULT lines stored under docs/runs/:
    each stored line's ratio is on the page, and the page holds no figure of its own (history: CHANGELOG.md)."""
    from gpnarx.training.pages import benchmarks as bench
    from gpnarx.training.pages.markdown import stored_run

    page = (DOCS / "benchmarks.md").read_text()
    assert page == bench.render(DOCS / "runs"), "docs/benchmarks.md differs from the render of docs/runs/bench/"
    stored = 0
    for rel, _, _ in bench.SOURCES:
        _, rows = stored_run((DOCS / "runs" / rel).read_text())
        for _, kv in rows:
            assert f"| {kv['ratio']} |" in page, kv
            stored += 1
    assert stored >= 10
    for script in sorted(p.name for p in (DOCS.parent / "bench").glob("bench_*.py")):
        assert f"`{script}`" in page, f"{script} is not in the method table"


def test_docs_monitoring_page_is_the_render_of_its_stored_runs():
    """docs/results-monitoring.md is studies.monitoring_page's render of docs/runs/monitoring (the cycle, torque and
    real-monitor studies' JSON and the facts of their bundles)."""
    from studies.monitoring_page import CYCLE_RUNS, render

    run = DOCS / "runs" / "monitoring"
    page = (DOCS / "results-monitoring.md").read_text()
    assert page == render(run), "docs/results-monitoring.md differs from its runs' render"
    for name, _ in CYCLE_RUNS:
        r = json.loads((run / name).read_text())
        assert f"| {r['energy_mean']:.4g} J |" in page, name


def test_docs_standin_page_is_the_render_of_its_stored_calibration():
    from studies.standin_page import render

    cal = json.loads((DOCS / "runs" / "standin" / "calibration.json").read_text())
    page = (DOCS / "standin.md").read_text()
    assert page == render(cal), "docs/standin.md differs from its stored calibration's render"
    for r in cal["rows"]:
        assert f"| {r['freq']:.2f} | {r['volts']:.4f} | {r['real']:.4g} | {r['standin']:.4g} |" in page


def test_the_renderers_command_line_writes_each_page_of_its_stored_run(tmp_path):
    """``python -m gpnarx.training.pages NAME RUN_DIR OUT.md`` writes what the page's test renders (one of each
    kind: the benches' RESULT lines, a study page, a protocol page)."""
    from gpnarx.training.pages.__main__ import main

    for name, run, page in (("benchmarks", "runs", "benchmarks.md"), ("standin", "runs/standin", "standin.md"),
                            ("bouc-wen", "runs/bouc-wen", "results-bouc-wen.md")):
        out = tmp_path / page
        assert main([name, str(DOCS / run), str(out)]) == 0
        assert out.read_text() == (DOCS / page).read_text(), name
    assert main(["no-such-page", "x", "y"]) == 2
