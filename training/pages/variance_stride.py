"""docs/numerics.md's table of the strided variance (eq. 9 at every s-th step of the linearised run, interpolated
between): a block of that page rendered from the stored run of studies/variance_stride_study.py
(docs/runs/variance-stride/table.json): ``python studies/variance_stride_study.py --render docs/numerics.md
--from-run docs/runs/variance-stride/table.json``."""
from __future__ import annotations

from gpnarx.training.pages.markdown import row, rule

BEGIN = ("<!-- variance-stride: rendered by studies/variance_stride_study.py from "
         "docs/runs/variance-stride/table.json -->")
END = "<!-- /variance-stride -->"


def _pct(v: float) -> str:
    return f"{100.0 * float(v):.2f} %"


def worst(table: dict, band: str = "gp") -> dict:
    """{stride: the largest band difference over the records} for ``band`` ('gp' or 'product')."""
    return {s: max(r[band][str(s)] for r in table["records"]) for s in table["strides"]}


def render(table: dict) -> str:
    """The block: one row per record, the band's largest difference at each stride, GP band and product band."""
    strides = table["strides"]
    bound = float(table.get("bound", 0.01))
    head = ["record", "samples"] + [f"s = {s}: GP band" for s in strides] + [f"s = {s}: answered band"
                                                                              for s in strides]
    lines = [BEGIN, "",
             f"Model `{table['model']}` ({table['posterior']} posterior, {table['n_points']} points, ny "
             f"{table['ny']}, nu {table['nu']}); each record whole, from rest, linearised. A cell is the band's "
             "largest difference from the exact one (eq. 9 at every step), max over samples of max(|lower_s - "
             "lower_1|, |upper_s - upper_1|) / half-width_1: the GP's own band, and the band the product answers "
             "with (widened by the bundle's model-discrepancy term" + ("" if table.get("discrepancy") else
                                                                       ", which this bundle has not")
             + f"). Code {table['code']}; stored run: `docs/runs/variance-stride/table.json`.", "",
             row(head), rule(len(head))]
    for r in table["records"]:
        lines.append(row([f"`{r['record']}`", str(r["n"])] + [_pct(r["gp"][str(s)]) for s in strides]
                         + [_pct(r["product"][str(s)]) for s in strides]))
    gp, prod = worst(table, "gp"), worst(table, "product")
    lines.append(row(["**largest**", ""] + [f"**{_pct(gp[s])}**" for s in strides]
                     + [f"**{_pct(prod[s])}**" for s in strides]))
    within = [s for s in strides if gp[s] <= bound]
    lines += ["", (f"Within {_pct(bound)} of the half-width on every record (GP band): "
                   + (", ".join(f"s = {s}" for s in within) if within else "no stride") + ".")]
    secs = {s: sum(r["seconds"][str(s)] for r in table["records"]) for s in [1] + strides}
    lines += ["", "Free-run seconds over all records, this run's machine and load (" + table["machine"]
              + f", load {table['load']:.1f}): " + ", ".join(f"s = {s}: {secs[s]:.1f} s" for s in [1] + strides)
              + ".", "", END]
    return "\n".join(lines)
