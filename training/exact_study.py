"""The exact real-rig model on every real record: docs/runs/bert-real-exact and docs/results-bert-real-exact.md.

``bert-real`` trained in exact mode (``gpnarx train bert-real --mode exact --name bert-real-exact``: the full GP
on the config's 1,500 ML-II rows instead of the shipped sparse posterior) and scored by the same every-record
class table as docs/results-bert-real.md (``training.real_table``, linearised whole records, the same ARX lag
search), next to the shipped model's figures from its stored run.

    python -m gpnarx.training.exact_study run BUNDLE_DIR docs/runs/bert-real-exact
    python -m gpnarx.training.exact_study render docs/runs/bert-real-exact docs/results-bert-real-exact.md
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .real_table import markdown

ARX_GRID = ([8, 16, 24, 32], [10, 20, 30])  # the shipped run's lag surface (docs/runs/bert-real)


def run(bundle_dir, out_dir, log=print) -> dict:
    from ..model.bundle import load_bundle
    from .config import bert_data_dir, load_config
    from .defaults import shipped_config
    from .real_table import real_table, table_checks

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    b = load_bundle(bundle_dir)
    cfg = load_config(shipped_config("bert-real"))
    t0 = time.perf_counter()
    table = real_table(b.model, cfg, bert_data_dir(), mc_paths=0, lag_grid=ARX_GRID, lag_criterion="worst", log=log)
    summary = {"bundle": f"{b.name}:{b.version}", "mode": b.manifest["mode"], "n_train": b.manifest["n_train"],
               "command": "gpnarx train bert-real --mode exact --name bert-real-exact", "real_table": table,
               "checks": table_checks(table), "seconds": time.perf_counter() - t0}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def _heldout_fits(table: dict) -> dict:
    return {n: r["whole_linear"]["fit"] for n, r in table["records"].items() if r["role"] == "validate"}


def render(summary: dict, shipped: dict) -> str:
    """The page from this run's summary and the shipped model's stored run (docs/runs/bert-real/summary.json)."""
    table, checks = summary["real_table"], summary["checks"]
    mine, theirs = _heldout_fits(table), _heldout_fits(shipped["real_table"])
    lines = ["# Results: the exact real-rig model on every real record\n",
             "Rendered by `python -m gpnarx.training.exact_study render docs/runs/bert-real-exact "
             "docs/results-bert-real-exact.md` from the stored run (`run` writes it). The model: "
             f"`{summary['command']}` ({summary['mode']} posterior on {summary['n_train']} rows; everything else is "
             "the shipped `bert-real` config). The table is the one of [results-bert-real.md](results-bert-real.md), "
             "linearised whole records from rest.\n",
             "## Held-out records against the shipped sparse model\n",
             "| held-out record | exact fit % | shipped fit % | better ARX fit % |", "|---|---|---|---|"]
    for name in sorted(mine):
        r = table["records"][name]
        arx = max((x for x in (r["arx_search"]["fit"], r["arx_class"]["fit"]) if x is not None), default=None)
        lines.append(f"| {name} | {_f(mine[name])} | {_f(theirs.get(name))} | {_f(arx)} |")
    lines += ["", "## Every record by class\n", markdown(table, checks)]
    return "\n".join(lines)


def _f(v) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 3 or argv[0] not in ("run", "render"):
        print(__doc__, file=sys.stderr)
        return 2
    if argv[0] == "run":
        run(argv[1], argv[2])
        return 0
    run_dir = Path(argv[1])
    summary = json.loads((run_dir / "summary.json").read_text())
    shipped = json.loads((run_dir.parent / "bert-real" / "summary.json").read_text())
    Path(argv[2]).write_text(render(summary, shipped))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
