"""The free-run fits a choice is made by: the lag surface (``training.lags``) and the lengthscale refinement
(``training.hyper_refine``) score each candidate model by them on the config's 'lags' records."""
from __future__ import annotations

import numpy as np

from gpnarx.model.metrics import fit_percent


def free_run_fits(model, records, score_clean: bool = False) -> dict:
    """Free-run fit % (eq. 14) of the linearised mean of each record, from its start rule (the first ny measured
    outputs when ``meta.initial`` is "measured", else rest), against ``meta.clean_y`` with ``score_clean`` (the
    record's y without one); -1000 where not finite (a diverged run). ``{record name: fit}``."""
    fits = {}
    for rec in records:
        y0 = rec.y[: model.ny] if rec.meta.get("initial") == "measured" else None  # steady-state records
        run = model.simulate(rec.u, method="linear", y0=y0)
        ref = rec.meta.get("clean_y", rec.y) if score_clean else rec.y
        f = fit_percent(ref, run.mean)
        fits[rec.name] = float(f) if np.isfinite(f) else -1e3
    return fits
