"""Held-out calibration of the likelihood noise variance sigma_y^2 (eq. 2).

ML-II (eq. 13) can drive sigma_y^2 to its lower bound when the GP interpolates its training rows:
on the real BERT records it stops at 1e-8 (standardised), about the laser vibrometer's own noise floor
(2.6e-9 to 9.8e-9) and 3-24x under the one-step error on records not trained on. The posterior is then
built from an ill-conditioned system, eq. 9's variance cancels to zero on most regressors, and
the free-run 99% bands are far too narrow.

``heldout_noise_var`` estimates sigma_y^2 from one-step-ahead residuals r_i on held-out records
(measured lags, not trained on) by maximising their mean log predictive density under eq. 2,

    sigma^2 = argmax  mean_i log N(r_i; 0, v_i + sigma^2),     sigma^2 in [floor, ceiling],

where v_i is the posterior latent variance of eq. 9 at that regressor. ``GPNARX.fit(...,
heldout=records)`` raises sigma_y^2 to this value (never lowers it below ML-II's) and rebuilds the
posterior with it; the kernel hyperparameters stay at their ML-II values.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from .ml2 import NOISE_LOG_BOUNDS

NOISE_CEILING = float(np.exp(NOISE_LOG_BOUNDS[1]))  # standardised units; ML-II's upper bound


def heldout_noise_var(residual, latent_var, floor: float, ceiling: float = NOISE_CEILING) -> float:
    """Held-out maximum-likelihood noise variance (standardised output units squared).

    residual: one-step-ahead residuals y_i - mu_i on held-out records, standardised (1-D).
    latent_var: posterior latent variance v_i of eq. 9 at the same regressors (>= 0, 1-D).
    floor, ceiling: bounds on sigma^2 (floor > 0, typically the ML-II sigma_y^2).
    Returns the sigma^2 in [floor, ceiling] maximising mean log N(r_i; 0, v_i + sigma^2).
    """
    r = np.asarray(residual, dtype=float).ravel()
    v = np.asarray(latent_var, dtype=float).ravel()
    if r.size == 0:
        raise ValueError("residual is empty: the held-out records give no one-step residuals")
    if v.shape != r.shape:
        raise ValueError(f"latent_var has {v.size} values for {r.size} residuals")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(v))):
        raise ValueError("residual and latent_var must be finite")
    if not 0 < floor <= ceiling:
        raise ValueError(f"need 0 < floor <= ceiling, got floor={floor!r}, ceiling={ceiling!r}")
    v = np.maximum(v, 0.0)
    r2 = r * r

    def nlpd(log_s2: float) -> float:
        s = v + np.exp(log_s2)
        return 0.5 * float(np.mean(np.log(s) + r2 / s))

    lo, hi = np.log(floor), np.log(ceiling)
    if hi - lo < 1e-12:
        return float(floor)
    res = minimize_scalar(nlpd, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    best = float(res.x)
    # the bounded search never evaluates the ends exactly; keep an end when it is better
    for end, value in ((lo, floor), (hi, ceiling)):
        if nlpd(end) <= nlpd(best):
            return float(value)
    return float(min(max(np.exp(best), floor), ceiling))


__all__ = ["heldout_noise_var", "NOISE_CEILING"]
