"""The linearised free run one posterior call per step: eq. 8-9 and the mean's gradient at the mean regressor
(``mean_grad``), then one step of the covariance recursion. It runs any posterior with ``mean_grad`` and
``noise_var``: those the three-pass run (``linear``) cannot take (not a ``posterior.Posterior``, or a kernel
without ``MeanTerms``); the three-pass run gives its numbers to round-off (tests/test_freerun_fast.py).
"""
from __future__ import annotations

import time

import numpy as np

from ..normal import band_z
from .results import FreeRun
from .spec import LAG_CLIP, VAR_CAP, Predictor, RunSpec, check_confidence, start_index


def run_linear_stepwise(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    """The linearised free run of ``u`` (input units) as ``linear.run_linear`` describes it, one ``mean_grad`` call
    per step; every run starts anew (a ``spec.state`` is refused)."""
    if spec.state is not None:
        raise ValueError("state: the stepwise linearised run starts anew; its posterior cannot continue a stream")
    ny, nu, posterior = predictor.ny, predictor.nu, predictor.posterior
    t_start = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    n = u.size
    i0, y0v = start_index(n, ny, spec.y0)
    mean = np.zeros(n)
    std = np.zeros(n)
    lstd = np.zeros(n)  # latent std: var(y_i) without the reporting step's sigma_y^2
    if i0:
        mean[:i0] = y0v
    xm, xs = predictor.x_mean, predictor.x_scale
    ym, ys = predictor.y_mean, predictor.y_scale
    Ulag = predictor.input_lags(u)
    m = np.zeros(ny)
    if i0:
        m[:] = y0v[::-1]
    L = max(ny, int(spec.cov_window or 0))
    S = np.zeros((L, L))
    band = np.zeros((n, L)) if L > ny else None
    noise = predictor.noise(spec)
    x = np.empty(ny + nu)
    cap = VAR_CAP * ys * ys  # variance cap in output units
    for i in range(i0, n):
        x[:ny] = np.clip((m - xm[:ny]) / xs[:ny], -LAG_CLIP, LAG_CLIP)  # a diverging mean stays finite
        x[ny:] = Ulag[i]
        mu, var_f, grad = posterior.mean_grad(x)
        J = grad[:ny] / xs[:ny] * ys  # d mu_out / d y_lag (output units)
        SJ = S[:, :ny] @ J
        if not np.all(np.isfinite(SJ)):  # a diverging run keeps a finite state covariance
            SJ = np.nan_to_num(SJ, nan=cap, posinf=cap, neginf=-cap)
        np.clip(SJ, -cap, cap, out=SJ)
        var_y = (var_f + noise) * ys * ys + float(J @ SJ[:ny])
        var_y = min(var_y, cap) if np.isfinite(var_y) else cap
        y_mean = mu * ys + ym
        mean[i] = y_mean
        std[i] = np.sqrt(max(var_y, 0.0))
        var_f_out = var_f * ys * ys + float(J @ SJ[:ny])
        lstd[i] = np.sqrt(max(min(var_f_out, var_y), 0.0)) if np.isfinite(var_f_out) else std[i]
        # shift the state: new first element is y_i
        S[1:, 1:] = S[:-1, :-1]
        S[0, 1:] = SJ[:-1]
        S[1:, 0] = SJ[:-1]
        S[0, 0] = var_y
        if band is not None:
            band[i, 0] = var_y
            band[i, 1:] = SJ[:-1]
        m[1:] = m[:-1]
        m[0] = y_mean
        if spec.progress is not None and (i % 256 == 0 or i == n - 1):
            spec.progress(i + 1, n)
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t_start, n - i0, cov_band=band,
                   latent_lower=mean - z * lstd, latent_upper=mean + z * lstd)
