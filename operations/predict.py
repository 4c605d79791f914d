"""The predict operation: the free run's mean and band, and fit, RMSE and coverage when y is sent.

With ``horizon`` k, the k-step-ahead prediction (``model.freerun.horizon``: the run restarts from the measured
outputs every k samples); the answer says ``horizon``. A record with gaps (``model.gaps``: null / NaN runs in u or
y) is answered with NaN (JSON null) through each gap and the run restarted after it; the answer lists ``gaps``
and its fit and coverage skip them."""
from __future__ import annotations

from gpnarx.model.gaps import gap_list
from gpnarx.model.metrics import summary

from .base import Operation, finite_or_none, head


class Predict(Operation):
    name = "predict"
    takes_gaps = True

    def answer(self, plan, req, u, y, run, common, flags, checkpoint):
        b = plan.bundle
        out = {**head(b), "mean": run.mean, "lower": run.lower, "upper": run.upper, "std": run.std, **common,
               "n_samples": int(u.size), "units": dict(b.manifest.get("units") or {})}
        if plan.horizon is not None:
            out["horizon"] = plan.horizon
        if plan.gaps:
            out["gaps"] = gap_list(plan.gaps, float(b.fs))
        if y is None:
            return out, None, None
        s = summary(y, run.mean, run.lower, run.upper)
        out.update(fit=finite_or_none(s["fit"]), rmse=finite_or_none(s["rmse"]),
                   coverage=finite_or_none(s["coverage"]))
        return out, s, None
