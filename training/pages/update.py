"""docs/updates.md's real-rig block: an update from a held-back sine, before and after, from its stored run.

The run is ``studies/update_study.py``'s JSON (``docs/runs/update/bert-real-hold-19Hz.json``). The block sits between
``BEGIN`` and ``END`` in the page; the rest of the page is prose.

    python -m gpnarx.training.pages.update docs/runs/update/bert-real-hold-19Hz.json docs/updates.md
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from gpnarx.training.pages.markdown import pct, replace_block, sig, table

BEGIN = "<!-- update-run:begin (rendered by python -m gpnarx.training.pages.update; do not edit) -->"
END = "<!-- update-run:end -->"


def block(run: dict, run_path: str) -> str:
    """The rendered block (markers included) of the stored run ``run`` read from ``run_path`` (as the page names it)."""
    before, after, ref = run["before"], run["after"], run.get("reference")
    head = ["record", "fit before", "fit after", "coverage before", "coverage after"]
    if ref:
        head += [f"fit, {ref['bundle']}", f"coverage, {ref['bundle']}"]
    rows = []
    for name in before:
        cells = [f"`{name}`", pct(before[name]["fit"], 2), pct(after[name]["fit"], 2),
                 pct(before[name]["coverage"], 2), pct(after[name]["coverage"], 2)]
        if ref:
            r = ref["scores"][name]
            cells += [pct(r["fit"], 2), pct(r["coverage"], 2)]
        rows.append(cells)
    worst = {k: min(v[n]["fit"] for n in v) for k, v in (("before", before), ("after", after))}
    cov = {k: min(v[n]["coverage"] for n in v) for k, v in (("before", before), ("after", after))}
    lin, rows_info, steps = run["lineage"], run["lineage"]["rows"], run["steps"]
    recal = lin["recalibrated"]
    p, u = run["parent"], run["updated"]
    held = ", ".join(f"`{n}`" for n in run["held_back"])
    out = [BEGIN, "",
           f"Stored run: `{run_path}` (`studies/update_study.py`). The shipped `{run['config']}` without {held} was "
           f"trained as `{run['variant']}` ({sig(run['train_seconds'])} s, no report), then updated with those "
           f"{len(run['held_back'])} windows as new records ({sig(run['update_seconds'])} s: rank update "
           f"{sig(steps.get('rank_update', 0.0))} s, noise {sig(steps.get('noise', 0.0))} s, band "
           f"{sig(steps.get('band', 0.0))} s). Rows: {rows_info['rows_added']} added, {rows_info['rows_dropped']} "
           f"dropped by the selection rule, {rows_info['rows']} in the posterior (budget {rows_info['budget']}). "
           f"sigma_y^2 {sig(p['noise_var'])} -> {sig(u['noise_var'])} (standardised); band scale "
           f"{sig(p['band_scale'])} -> {sig(u['band_scale'])}"
           + (f"; novelty: {recal['novelty']}" if isinstance(recal.get("novelty"), str) else "") + ".",
           "",
           f"Scored on the config's `validate` records (no choice saw them), {run['propagation']['method']} free run "
           f"from each record's start rule: fit % (eq. 14) and 99 % coverage.",
           *([""] + [f"`{ref['bundle']}`: a model trained on every training record, the held-back sine included "
                     f"(ML-II chose its hyperparameters with it; {ref['n_train']} rows), scored the same way."]
             if ref else []),
           "", *table(head, rows), "",
           f"Worst fit {pct(worst['before'], 2)} before, {pct(worst['after'], 2)} after; lowest coverage "
           f"{pct(cov['before'], 2)} before, {pct(cov['after'], 2)} after.", "", END]
    return "\n".join(out)


def render_into(page: str, run: dict, run_path: str) -> str:
    """``page`` with its block replaced by the rendering of ``run``."""
    return replace_block(page, BEGIN, END, block(run, run_path))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: python -m gpnarx.training.pages.update RUN.json PAGE.md", file=sys.stderr)
        return 2
    run_path, page = Path(argv[0]), Path(argv[1])
    rel = run_path.resolve().as_posix()
    rel = rel[rel.index("docs/runs/"):] if "docs/runs/" in rel else run_path.as_posix()
    page.write_text(render_into(page.read_text(), json.loads(run_path.read_text()), rel))
    return 0


if __name__ == "__main__":
    sys.exit(main())
