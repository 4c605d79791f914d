"""The lag-surface choice rule and grid-edge check (section 2.2, step 2), on computed cells.

A cell is a dict with ``ny``, ``nu`` and ``fit`` (free-run fit %, eq. 14). Pure functions on cells,
shared by the lag surface (:mod:`gpnarx.training.lags`), which computes them, and the report
(:mod:`gpnarx.training.report`), which draws and tabulates them.

Choice rule ("the best fit with a minimal number of lags"): among cells whose fit is within
``tolerance`` (default 0.5) points of the best fit, take the smallest ny + nu; ties go to the
higher fit.

Grid edge: when the best cell lies on the largest ny or nu tried (and that axis has more than one
value), the fit may still rise beyond the grid. ``grid_edge`` lists such axes (for example
``["nu"]``) so the caller can warn and the user can extend the range; the choice itself is not
changed.
"""
from __future__ import annotations

import numpy as np

DEFAULT_TOLERANCE = 0.5


def choose_lags(cells: list[dict], tolerance: float = DEFAULT_TOLERANCE) -> dict:
    """The chosen cell by the documented rule (see module docstring)."""
    ok = [c for c in cells if c["fit"] is not None and np.isfinite(c["fit"])]
    if not ok:
        raise ValueError("no lag cell produced a finite fit")
    best = max(c["fit"] for c in ok)
    near = [c for c in ok if c["fit"] >= best - tolerance]
    return min(near, key=lambda c: (c["ny"] + c["nu"], -c["fit"]))


def grid_edge(cell: dict, ny_values, nu_values) -> list[str]:
    """Lag axes ("ny", "nu") on which ``cell`` sits at the largest value tried (axes of one value are
    never an edge: the user fixed them)."""
    edge = []
    for axis, values in (("ny", ny_values), ("nu", nu_values)):
        values = [int(v) for v in values]
        if len(set(values)) > 1 and int(cell[axis]) == max(values):
            edge.append(axis)
    return edge


def edge_message(surface: dict) -> str:
    """One line telling which lag axes the best cell reached the grid's largest value on."""
    best = surface["best"]
    axes = " and ".join(f"{a}={best[a]}" for a in surface["edge"])
    return (f"the best cell (ny={best['ny']}, nu={best['nu']}, fit {best['fit']:.2f} %) is at the largest "
            f"{axes} tried; the fit may still rise beyond the grid: extend "
            + " and ".join(f"--{a}" for a in surface["edge"]) + " to check")
