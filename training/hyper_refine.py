"""The kernel's lengthscales refined by free-run fit on the config's 'lags' records (``[model] lengthscale_refine``).

ML-II (eq. 13) fits the hyperparameters by the one-step-ahead likelihood; the product predicts by free run
(eqs. 8-9 fed back through the output lags). On the real rig the two disagree on broadband loads: the one-step
optimum interpolates the few broadband rows near the origin of the regressor space, and the free run of a
noise run drifts from the measured response, while a slightly smoother posterior follows it better and costs
the sines little. This step moves the stationary kernels' lengthscales (every ``lengthscale`` of the kernel's
parts, by one common factor; every other hyperparameter, the rows and the noise variance held) and keeps the
factor by the rule below, scored by the free run the product makes.

Rule: the free-run fit (eq. 14) of every 'lags' record, linearised, from its start rule (``meta.initial``),
at ML-II's lengthscales (factor 1) and at factors exp(+-k ``STEP``) stepping away from 1 in each direction (at
most ``MAX_STEPS`` each way: factors 0.37 to 2.7). A factor is admissible when no 'lags' record loses more than
``tolerance``
points of fit against factor 1 (default ``DEFAULT_TOLERANCE``): the refinement may trade a little on one class
for more on another, never a class for another. Among admissible factors the one with the best worst-record
fit is kept (ties: the one nearer 1). A direction stops at its first inadmissible factor, or when the worst
fit has not risen for two steps. Factor 1 always stays admissible, so the step never leaves the model worse
on its worst 'lags' record.

Each candidate refactors the exact posterior on its rows (``model.gp_update.refactor``, O(N^3)) and predicts
every 'lags' record once. Exact posterior only (a sparse one is left as ML-II gave it, and the step says so).
"""
from __future__ import annotations

import time

import numpy as np

from gpnarx.training.free_run_fits import free_run_fits

RULES = ("none", "lags")
STEP = 0.05  # factors exp(+/- k STEP)
MAX_STEPS = 20
DEFAULT_TOLERANCE = 1.0  # points of fit (eq. 14) a 'lags' record may lose against ML-II's lengthscales


def lengthscale_indices(kernel) -> list[int]:
    """Positions in the kernel's theta (``get_theta``) of every part's ``lengthscale``."""
    out, at = [], 0
    for part in kernel.parts:
        names = list(getattr(part, "param_names", ()))
        out += [at + i for i, n in enumerate(names) if n == "lengthscale"]
        at += len(names)
    return out


def _with_factor(model, theta0: np.ndarray, idx: list[int], factor: float, rows: tuple) -> None:
    """``model`` with its lengthscales ``factor`` x ML-II's (``theta0``, the kernel's log-hyperparameters) and
    the exact posterior refactored on its rows ``rows`` = (X, y), the noise variance held."""
    from gpnarx.model.gp_update import refactor

    theta = np.array(theta0, dtype=float)
    theta[idx] += np.log(factor)
    model.kernel_.set_theta(theta)
    model.theta_ = np.concatenate([theta, np.asarray(model.theta_, dtype=float)[-1:]])
    model.posterior_ = refactor(model._posterior_kernel(), model.noise_var_, *rows)


def _fits(model, records) -> dict:
    """``free_run_fits`` of the records against their measured y, a diverging candidate's warnings
    silenced (it scores -1000)."""
    with np.errstate(all="ignore"):
        return free_run_fits(model, records)


def refine_lengthscales(model, records, *, tolerance: float = DEFAULT_TOLERANCE, log=None) -> dict:
    """Refine the fitted exact ``model``'s lengthscales in place by the module's rule on ``records`` (the
    config's 'lags' records). Returns what was done (also ``model.hyper_refinement_``): the factor kept, every
    candidate's fits and the seconds taken."""
    from gpnarx.model.gp_update import targets

    log = log or (lambda msg: None)
    t0 = time.perf_counter()
    if not records:
        raise ValueError("lengthscale_refine: no record has role 'lags'")
    if not 0.0 <= float(tolerance) <= 100.0:
        raise ValueError(f"lengthscale_refine_tolerance must be between 0 and 100 points, got {tolerance!r}")
    post = model.posterior_
    idx = lengthscale_indices(model.kernel_)
    if post.kind != "exact" or not idx:
        why = "the posterior is sparse" if post.kind != "exact" else "the kernel has no lengthscale"
        model.hyper_refinement_ = {"rule": "lags", "factor": 1.0, "skipped": why}
        log(f"lengthscale refinement skipped: {why}")
        return model.hyper_refinement_
    rows = (post.X_train, targets(post))
    theta0 = model.kernel_.get_theta()
    fitted_post, fitted_theta = post, np.array(model.theta_, dtype=float)
    base = _fits(model, records)
    cands = [{"factor": 1.0, "fits": base, "worst": min(base.values()), "admissible": True}]
    log(f"lengthscale refinement on {len(records)} 'lags' record(s): factor 1 (ML-II) worst fit "
        f"{cands[0]['worst']:.2f} %")
    for sign in (+1, -1):
        best_here, stale = cands[0]["worst"], 0
        for k in range(1, MAX_STEPS + 1):
            factor = float(np.exp(sign * k * STEP))
            _with_factor(model, theta0, idx, factor, rows)
            fits = _fits(model, records)
            ok = all(fits[n] >= base[n] - tolerance for n in base)
            c = {"factor": factor, "fits": fits, "worst": min(fits.values()), "admissible": ok}
            cands.append(c)
            log(f"  factor {factor:.2f}: worst fit {c['worst']:.2f} %" + ("" if ok else " (a record lost more "
                f"than {tolerance:g} points: stop)"))
            if not ok:
                break
            stale = 0 if c["worst"] > best_here else stale + 1
            best_here = max(best_here, c["worst"])
            if stale >= 2:
                break
    ok = [c for c in cands if c["admissible"]]
    best = max(ok, key=lambda c: (round(c["worst"], 6), -abs(c["factor"] - 1.0)))
    if best["factor"] == 1.0:
        model.kernel_.set_theta(theta0)
        model.theta_, model.posterior_ = fitted_theta, fitted_post
    else:
        _with_factor(model, theta0, idx, best["factor"], rows)
    model.hyper_refinement_ = {"rule": "lags", "factor": float(best["factor"]), "tolerance": float(tolerance),
                               "records": list(base), "worst_fit_ml2": cands[0]["worst"],
                               "worst_fit": best["worst"], "candidates": cands,
                               "seconds": time.perf_counter() - t0}
    log(f"lengthscales x {best['factor']:.2f} (worst 'lags' fit {cands[0]['worst']:.2f} % -> {best['worst']:.2f} %, "
        f"{len(cands)} candidates, {model.hyper_refinement_['seconds']:.0f} s)")
    return model.hyper_refinement_


def markdown(refinement: dict) -> str:
    """What ``refine_lengthscales`` did (a bundle's ``hyper_refinement``) as Markdown: the rule's one line and
    every candidate's free-run fits on the 'lags' records."""
    cands = sorted(refinement.get("candidates") or [], key=lambda c: c["factor"])
    if not cands:
        return f"Lengthscales as ML-II fitted them ({refinement.get('skipped', 'no refinement')}).\n"
    names = list(refinement["records"])
    lines = [f"ML-II (eq. 13) fits the hyperparameters one step ahead; the product predicts by free run. The kernel's "
             f"lengthscales were moved by one factor and the factor kept by free-run fit on the `lags` records "
             f"(`[model] lengthscale_refine = \"lags\"`, `training/hyper_refine.py`): the best worst-record fit among "
             f"factors at which no `lags` record loses more than {refinement['tolerance']:g} points against ML-II's. "
             f"Kept: **x {refinement['factor']:.2f}**, worst `lags` fit {refinement['worst_fit_ml2']:.2f} % -> "
             f"{refinement['worst_fit']:.2f} % ({refinement.get('seconds', float('nan')):.0f} s of training).", "",
             "| lengthscale factor | " + " | ".join(f"{n} fit %" for n in names) + " | worst | admissible |",
             "|" + "---|" * (len(names) + 3)]
    for c in cands:
        mark = "**" if c["factor"] == refinement["factor"] else ""
        lines.append(f"| {mark}{c['factor']:.2f}{mark} | " + " | ".join(f"{c['fits'][n]:.2f}" for n in names)
                     + f" | {c['worst']:.2f} | {'yes' if c['admissible'] else 'no'} |")
    return "\n".join(lines) + "\n"
