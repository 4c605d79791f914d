"""The residual tests of the training report: for every ``verify`` and ``validate`` record, the one-step fit and
the whiteness and input cross-correlation tests of the one-step residuals (``model.residual_tests``).

``attach_residual_tests`` computes them with the fitted model and puts them in the record dicts the report is
written from (key ``residual_tests``); ``training.report.write_report`` writes them to report.json (each record's
``residual_tests``), as a table on the page and, where matplotlib is installed, as one figure per record
(``training.report_figures.residual_figure``). Only the one-step mean is computed (the tests use the raw
residuals; no one-step variance, whose triangular products cost more than the mean on a 64 s record).
"""
from __future__ import annotations

from gpnarx.model.residual_tests import DEFAULT_CONFIDENCE, DEFAULT_LAGS, one_step_check

#: the roles whose records get the residual tests (the records that check the model, not those it chose by)
RESIDUAL_ROLES = ("verify", "validate")


def attach_residual_tests(model, records: list[dict], lags: int = DEFAULT_LAGS,
                          confidence: float = DEFAULT_CONFIDENCE) -> list[dict]:
    """``records`` (report record dicts: ``role``, ``u``, ``y``), each of a role in ``RESIDUAL_ROLES`` with a
    measured ``y`` given ``residual_tests``: ``model.residual_tests.one_step_check``'s dict (``n``, ``fit``,
    ``rmse``, ``residual_tests``), or {``error``} where the record cannot be tested (too short for the lags, a
    gap). A record under both roles is predicted once. Returns ``records`` (changed in place)."""
    done: dict = {}
    for rec in records:
        if rec.get("role") not in RESIDUAL_ROLES or rec.get("y") is None or rec.get("u") is None:
            continue
        key = (rec.get("name"), id(rec["u"]), id(rec["y"]))
        if key not in done:
            try:
                done[key] = one_step_check(model, rec["u"], rec["y"], lags=lags, confidence=confidence)
            except ValueError as exc:
                done[key] = {"error": str(exc)}
        rec["residual_tests"] = done[key]
    return records
