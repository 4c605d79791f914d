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
    """docs/results-accelerator.md is what training.accelerator_page renders from docs/runs/accelerator/ (the
    GPU run of bench/bench_gpu.py and training/rows_study.py): every figure on it comes from that run."""
    from gpnarx.training.accelerator_page import render

    run = DOCS / "runs" / "accelerator"
    page = (DOCS / "results-accelerator.md").read_text()
    assert page == render(run), "docs/results-accelerator.md differs from its run's render"
    bench = [ln for ln in (run / "bench_gpu.txt").read_text().splitlines() if ln.startswith("RESULT ")]
    assert bench and all("device=gpu" in ln for ln in bench)
    rows = json.loads((run / "rows_study.json").read_text())
    for r in rows["rows"]:
        assert f"| exact, N = {r['n_train']} |" in page


def test_docs_exact_real_page_is_the_render_of_its_stored_run():
    """docs/results-bert-real-exact.md is training.exact_study's render of docs/runs/bert-real-exact (and of the
    shipped model's stored run it is set against)."""
    from gpnarx.training.exact_study import render

    summary = json.loads((DOCS / "runs" / "bert-real-exact" / "summary.json").read_text())
    shipped = json.loads((DOCS / "runs" / "bert-real" / "summary.json").read_text())
    split = json.loads((DOCS / "runs" / "bert-real-exact" / "split_study.json").read_text())
    page = (DOCS / "results-bert-real-exact.md").read_text()
    assert page == render(summary, shipped, split), "docs/results-bert-real-exact.md differs from its run's render"
    assert summary["mode"] == "exact"
    for cell in split["cells"]:  # every cell of the split study is on the page, with its worst 'lags' fit
        assert f"| {cell['noise_split']:g} | " in page and f"{cell['worst_lags_fit']:.1f}" in page
    for name, r in summary["real_table"]["records"].items():
        if r["role"] == "validate":
            assert f"| {name} | {r['whole_linear']['fit']:.1f} |" in page, name
