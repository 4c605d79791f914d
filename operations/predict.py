"""The predict operation: the free run's mean and band, and fit, RMSE and coverage when y is sent."""
from __future__ import annotations

from gpnarx.model.metrics import summary

from .base import Operation, finite_or_none, head


class Predict(Operation):
    name = "predict"

    def answer(self, plan, req, u, y, run, common, flags, checkpoint):
        b = plan.bundle
        out = {**head(b), "mean": run.mean, "lower": run.lower, "upper": run.upper, "std": run.std, **common,
               "n_samples": int(u.size), "units": dict(b.manifest.get("units") or {})}
        if y is None:
            return out, None, None
        s = summary(y, run.mean, run.lower, run.upper)
        out.update(fit=finite_or_none(s["fit"]), rmse=finite_or_none(s["rmse"]),
                   coverage=finite_or_none(s["coverage"]))
        return out, s, None
