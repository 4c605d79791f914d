"""Reference free runs: the plain one-step-at-a-time loops that ``freerun.simulate_linear`` and
``freerun.simulate_mc`` must agree with. ``simulate_linear_reference`` calls the posterior's eq. 8-9 and mean
gradient once per step; ``simulate_mc_reference`` evaluates eq. 8-9 exactly at every Monte Carlo path
(no local model). Kept as the baselines of the equivalence tests and of the speed benchmarks; the
product's answers come from ``model.freerun``.
"""
from __future__ import annotations

import time

import numpy as np

from ..normal import band_z
from .results import LAG_CLIP, VAR_CAP, FreeRun, McPaths, check_confidence, lagged_inputs, start_index


def simulate_linear_reference(
    posterior,
    x_scaler,
    y_scaler,
    ny: int,
    nu: int,
    u: np.ndarray,
    y0=None,
    confidence: float = 0.99,
    include_noise: bool = True,
    progress=None,
    cov_window: int = 0,
    state=None,
) -> FreeRun:
    """Reference implementation of ``simulate_linear`` (one ``posterior.mean_grad`` call per step),
    kept for posteriors without ``mean_var_grad``, for the equivalence tests and for
    bench/bench_realtime.py. Same arguments and result, except that it starts every run anew: a
    ``state`` (a stream's continuation) is refused.

    First-order (linearised) propagation of mean and covariance through the lagged outputs.

    State: mean m and covariance S (ny x ny) of [y_{i-1}, ..., y_{i-ny}] (output units). With
    J = d mu / d y_lags at the mean regressor (chain rule through the standardisation):
    var(y_i) = sigma_f^2 + sigma_y^2 + J S J^T, cov(y_i, y_{i-k}) = (S J^T)_k; the state shifts.

    cov_window: when L = cov_window > ny, the covariance state covers the last L outputs (J is
    zero beyond the ny lags, so mean and std are unchanged) and ``FreeRun.cov_band`` holds
    cov(y_i, y_{i-k}) for k < L, shape (n, L): what a linear functional of a window of outputs
    (e.g. a cycle's energy, ``model.cycles``) needs for its variance.
    """
    if state is not None:
        raise ValueError("state: the reference linearised run starts anew; continue streams with simulate_linear")
    t_start = time.perf_counter()
    confidence = check_confidence(confidence)
    z = band_z(confidence)
    n = u.size
    i0, y0v = start_index(n, ny, y0)
    mean = np.zeros(n)
    std = np.zeros(n)
    lstd = np.zeros(n)  # latent std: var(y_i) without the reporting step's sigma_y^2
    if i0:
        mean[:i0] = y0v
    xm, xs = x_scaler.mean_, x_scaler.scale_
    ym, ys = float(y_scaler.mean_[0]), float(y_scaler.scale_[0])
    Ulag = (lagged_inputs(u, nu) - xm[ny:]) / xs[ny:]
    m = np.zeros(ny)
    if i0:
        m[:] = y0v[::-1]
    L = max(ny, int(cov_window or 0))
    S = np.zeros((L, L))
    band = np.zeros((n, L)) if L > ny else None
    noise = posterior.noise_var if include_noise else 0.0
    x = np.empty(ny + nu)
    dscale = ys / xs[:ny]  # d y_out / d x_std for the lag columns
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
        if progress is not None and (i % 256 == 0 or i == n - 1):
            progress(i + 1, n)
    del dscale
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t_start, n - i0, cov_band=band,
                   latent_lower=mean - z * lstd, latent_upper=mean + z * lstd)


def simulate_mc_reference(
    posterior,
    x_scaler,
    y_scaler,
    ny: int,
    nu: int,
    u: np.ndarray,
    n_paths: int = 1024,
    seed: int | None = 0,
    y0=None,
    confidence: float = 0.99,
    include_noise: bool = True,
    float32: bool = False,
    keep_paths: bool = False,
    progress=None,
    diverge_limit: float | None = None,
    latent: bool = True,
    state=None,
) -> FreeRun:
    """Reference implementation of ``freerun.simulate_mc`` (same arguments but ``local``, same result):
    every step evaluates eq. 8 and eq. 9 at every path (``posterior.predict``). Kept for the equivalence
    tests and bench/bench_mc_speed.py. A ``state`` continues its paths and generator; the result carries
    no end state.
    """
    st = McPaths(posterior, x_scaler, y_scaler, ny, nu, u, n_paths, seed, y0, confidence, include_noise,
                 keep_paths, latent, state)
    xm, xs, Xs, n = st.xm, st.xs, st.Xs, st.n
    for i in range(st.i0, n):
        np.subtract(st.ylag_raw, xm[:ny], out=Xs[:, :ny])
        Xs[:, :ny] /= xs[:ny]
        np.clip(Xs[:, :ny], -LAG_CLIP, LAG_CLIP, out=Xs[:, :ny])  # a diverging path cannot overflow
        Xs[:, ny:] = st.Ulag[i]
        mu, var = posterior.predict(Xs, float32=float32)
        st.draw(i, mu, var)
        if progress is not None and (i % 256 == 0 or i == n - 1):
            progress(i + 1, n)
    return st.result(diverge_limit)
