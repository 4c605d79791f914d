"""k-step-ahead prediction: the free run restarted from the measured outputs every k samples (MATLAB's
``compare(data, sys, k)``).

The record's first ny measured outputs start the run, as a free run from measured outputs
(``RunSpec.y0``); then at samples ny, ny + k, ny + 2k, ... the output lags are set back to the measured
y_{s-1} .. y_{s-ny}, with no uncertainty, and the run goes on for k samples. So the sample s + j (0 <= j < k)
of a segment is predicted j + 1 steps ahead of the last measured output it uses. Input lags are the record's
own throughout (zeros before its first sample, as the free run).

* k = 1: every sample one step ahead of measured lags: eqs. 8-9 at measured regressors, for either method in
  closed form (one step from known lags is Gaussian; a Monte Carlo of it would only estimate that Gaussian):
  the numbers of ``GPNARX.predict_one_step``.
* k >= the record's predicted length (n - ny): one segment, the free run from the measured start itself.
* 1 < k: linearised, the segments run as one batch (S = ceil((n - ny) / k) regressors a step, k steps, the
  propagation of ``linear_stepwise`` per segment: mean and covariance of the output lags reset at each start);
  Monte Carlo, the paths of one run (``mc.run_mc``) whose lags are all set to the measured ones at each
  segment's start (one random stream: the same seed, the same answer).

The band is eqs. 8-9's, propagated over the at most k steps since the last measured outputs (sigma_y^2
included as ``include_noise`` says, as in ``predict_one_step``): the band of a k-step answer is the uncertainty
of a k-step prediction. The free run's model-discrepancy term (``model.discrepancy``) is not added: it is
calibrated on whole free runs, whose model-form error grows over the record, and would widen a one-step band
by the error of a whole run.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from gpnarx.checks import is_int

from ..normal import band_z
from .linear import run_linear
from .mc import run_mc
from .results import FreeRun
from .spec import LAG_CLIP, VAR_CAP, Predictor, RunSpec, check_confidence, lagged_inputs

#: floats of K(X_block, points) in one block of the closed-form one-step evaluation: 4 Mi (32 MiB), as the
#: estimator's row blocks (``estimator.ROW_BLOCK_FLOATS``); a block holds a multiple of 256 rows
_ONE_STEP_FLOATS = 1 << 22


def check_horizon(horizon, y, n: int) -> int:
    """``horizon`` as an int >= 1 when ``y`` (the measured output, n samples) is given; a ValueError naming
    ``horizon`` or ``y`` otherwise."""
    if not is_int(horizon, 1):
        raise ValueError(f"horizon must be an integer >= 1 (samples between restarts from the measured outputs), "
                         f"got {horizon!r}")
    if y is None:
        raise ValueError("y: a k-step prediction (horizon) restarts from the measured outputs every k samples; "
                         "send the record's measured output y")
    if np.asarray(y).size != n:
        raise ValueError(f"y has {np.asarray(y).size} samples but u has {n}; they must have the same length")
    return int(horizon)


def run_horizon(predictor: Predictor, u: np.ndarray, y: np.ndarray, spec: RunSpec, horizon: int,
                batch: bool | None = None) -> FreeRun:
    """The k-step-ahead prediction (k = ``horizon`` samples) of the record (u [input units], y [output units]),
    gap-free and longer than ny samples; see the module docstring. ``spec``: method, paths, seed, confidence,
    include_noise (its start, state and backend do not apply: numpy). ``batch``: the linearised segments as one
    batch (None: when there are two or more segments)."""
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    n, ny = u.size, predictor.ny
    k = check_horizon(horizon, y, n)
    if n <= ny:
        raise ValueError(f"u must be longer than ny={ny} samples for a k-step prediction, got {n}")
    if not np.all(np.isfinite(y)):
        raise ValueError("y holds non-finite values")
    spec = replace(spec, y0=y[:ny], state=None, keep_paths=False, cov_window=0)
    if k == 1:
        return _one_step(predictor, u, y, spec)
    if spec.method == "linear":
        one_segment = n - ny <= k
        if batch or (batch is None and not one_segment):
            return _linear_batch(predictor, u, y, spec, k)
        return run_linear(predictor, u, spec)  # one segment: the free run from the measured start
    if spec.method != "mc":
        raise ValueError(f"method must be 'mc' or 'linear', got {spec.method!r}")
    restarts = {s: y[s - ny: s][::-1].copy() for s in range(ny + k, n, k)}
    run = run_mc(predictor, u, spec, restarts=restarts)
    if restarts:
        run.state = None  # the lags were reset: no stream continues from it
    return run


def _one_step(predictor: Predictor, u, y, spec: RunSpec) -> FreeRun:
    """k = 1: eqs. 8-9 at the measured regressors of samples ny .. n - 1, in closed form."""
    t0 = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    n, ny = u.size, predictor.ny
    xm, xs, ym, ys = predictor.x_mean, predictor.x_scale, predictor.y_mean, predictor.y_scale
    rows = n - ny
    X = np.empty((rows, ny + predictor.nu))
    for j in range(1, ny + 1):  # y_{i-j}
        X[:, j - 1] = y[ny - j: n - j]
    X[:, :ny] -= xm[:ny]
    X[:, :ny] /= xs[:ny]
    X[:, ny:] = predictor.input_lags(u)[ny:]
    mu, var = np.empty(rows), np.empty(rows)
    block = max(256, _ONE_STEP_FLOATS // max(1, int(predictor.posterior.n_points)) // 256 * 256)
    for r0 in range(0, rows, block):
        r1 = min(rows, r0 + block)
        mu[r0:r1], var[r0:r1] = predictor.posterior.predict(X[r0:r1])
    noise = predictor.noise(spec)
    mean, std, lstd = y.copy(), np.zeros(n), np.zeros(n)
    mean[ny:] = mu * ys + ym
    std[ny:] = np.sqrt(var + noise) * ys
    lstd[ny:] = np.sqrt(var) * ys
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, spec.method,
                   time.perf_counter() - t0, rows, latent_lower=mean - z * lstd, latent_upper=mean + z * lstd)


#: floats of one group's lag covariances (segments x ny x ny) in ``_linear_batch``: 4 Mi (32 MiB)
_GROUP_FLOATS = 1 << 22
#: most segments of one group in ``_linear_batch`` (rows of one ``mean_var_grad`` call a step)
_GROUP_ROWS = 4096


def _linear_batch(predictor: Predictor, u, y, spec: RunSpec, k: int) -> FreeRun:
    """1 < k, linearised: every segment one row of a batch, k steps of ``mean_var_grad`` on the segments' rows;
    per segment the stepwise propagation (``linear_stepwise``), the lags' mean and covariance reset at its start.
    The segments run in groups of at most ``_GROUP_ROWS``, and of at most ``_GROUP_FLOATS`` floats of lag
    covariance (segments are independent: the same numbers as one batch, bounded memory)."""
    t0 = time.perf_counter()
    confidence = check_confidence(spec.confidence)
    z = band_z(confidence)
    n, ny, nu = u.size, predictor.ny, predictor.nu
    xm, xs = predictor.x_mean, predictor.x_scale
    starts = np.arange(ny, n, k)
    # standardised input lags, padded past the record's end (the last segment's extra steps are dropped)
    Ulag = (lagged_inputs(np.concatenate([u, np.zeros(k)]), nu) - xm[ny:]) / xs[ny:]
    out = np.zeros((3, starts.size, k))  # mean, variance, latent variance of every segment's steps
    group = max(1, min(_GROUP_ROWS, _GROUP_FLOATS // (ny * ny)))
    for g0 in range(0, starts.size, group):
        _linear_group(predictor, y, starts[g0: g0 + group], Ulag, spec, k, out[:, g0: g0 + group])
        if spec.progress is not None:
            spec.progress(min(n, ny + (g0 + group) * k), n)
    mean, std, lstd = y.copy(), np.zeros(n), np.zeros(n)
    mean[ny:] = out[0].ravel()[: n - ny]
    std[ny:] = np.sqrt(np.maximum(out[1].ravel()[: n - ny], 0.0))
    lstd[ny:] = np.sqrt(np.maximum(out[2].ravel()[: n - ny], 0.0))
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t0, n - ny, latent_lower=mean - z * lstd, latent_upper=mean + z * lstd)


def _linear_group(predictor: Predictor, y, starts, Ulag, spec: RunSpec, k: int, out) -> None:
    """The k steps of the segments starting at ``starts`` into ``out`` (3, segments, k): mean [output units],
    variance and latent variance [output units^2]."""
    posterior, ny, nu = predictor.posterior, predictor.ny, predictor.nu
    xm, xs, ym, ys = predictor.x_mean, predictor.x_scale, predictor.y_mean, predictor.y_scale
    S = starts.size
    m = np.stack([y[s - ny: s][::-1] for s in starts])  # (S, ny) lag means, newest first, output units
    C = np.zeros((S, ny, ny))  # covariance of the lags (output units^2)
    noise = predictor.noise(spec)
    cap = VAR_CAP * ys * ys
    X = np.empty((S, ny + nu))
    scale = ys / xs[:ny]
    for t in range(k):
        np.subtract(m, xm[:ny], out=X[:, :ny])
        X[:, :ny] /= xs[:ny]
        np.clip(X[:, :ny], -LAG_CLIP, LAG_CLIP, out=X[:, :ny])
        X[:, ny:] = Ulag[starts + t]
        mu, var_f, grad = posterior.mean_var_grad(X)
        J = grad[:, :ny] * scale
        SJ = np.einsum("sab,sb->sa", C, J)
        if not np.all(np.isfinite(SJ)):  # a diverging segment keeps a finite covariance, as the free run
            SJ = np.nan_to_num(SJ, nan=cap, posinf=cap, neginf=-cap)
        np.clip(SJ, -cap, cap, out=SJ)
        prop = np.einsum("sa,sa->s", J, SJ)
        v = (var_f + noise) * (ys * ys) + prop
        v = np.where(np.isfinite(v), np.minimum(v, cap), cap)
        ymean = mu * ys + ym
        out[0, :, t], out[1, :, t] = ymean, v
        lat = var_f * (ys * ys) + prop
        out[2, :, t] = np.where(np.isfinite(lat), np.minimum(lat, v), v)
        m[:, 1:] = m[:, :-1].copy()
        m[:, 0] = ymean
        C[:, 1:, 1:] = C[:, :-1, :-1].copy()
        C[:, 0, 0] = v
        C[:, 0, 1:] = SJ[:, :-1]
        C[:, 1:, 0] = SJ[:, :-1]


def join_runs(n: int, parts: list[tuple[int, FreeRun]]) -> FreeRun:
    """One ``FreeRun`` of n samples from runs of its pieces, ``parts`` = [(first sample, run), ...] in order;
    NaN where no piece lies (a gap). Path-steps, local steps and seconds add up; ``diverged_paths`` is the most
    any piece counted; no state (a record with gaps does not continue as a stream)."""
    first = parts[0][1]
    arrays = {}
    for name in ("mean", "std", "lower", "upper", "latent_lower", "latent_upper"):
        if name.startswith("latent") and any(getattr(r, name) is None for _, r in parts):
            arrays[name] = None
            continue
        a = np.full(n, np.nan)
        for at, r in parts:
            v = getattr(r, name)
            a[at: at + v.size] = v
        arrays[name] = a
    return FreeRun(arrays["mean"], arrays["std"], arrays["lower"], arrays["upper"], first.confidence,
                   max(r.n_paths for _, r in parts), first.method, sum(r.seconds for _, r in parts),
                   sum(r.path_steps for _, r in parts), diverged_paths=max(r.diverged_paths for _, r in parts),
                   local_steps=sum(r.local_steps for _, r in parts), latent_lower=arrays["latent_lower"],
                   latent_upper=arrays["latent_upper"], backend=first.backend)
