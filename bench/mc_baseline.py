"""The Monte Carlo step before the fused local model, kept as the benchmarks' baseline (``bench_mc_speed``).

A verbatim copy of the previous product code: ``freerun.simulate_mc`` with its ``_local_step``,
``gp.local_model`` (one call per kernel part for k, J and each Hessian) and ``freerun_core.McPaths``
(the lags shifted by a (P x ny) copy every step). Same seed, same numbers as the product up to
round-off; not part of the package.
"""
from __future__ import annotations

import time

import numpy as np

from gpnarx.model.freerun import (
    LOCAL_BACKOFF,
    LOCAL_CHECKS,
    LOCAL_EXACT_SHARE,
    LOCAL_MIN_PATHS,
    LOCAL_TOL_MEAN,
    LOCAL_TOL_VAR,
)
from gpnarx.model.freerun.mc_local import has_local_model
from gpnarx.model.freerun.results import (
    LAG_CLIP,
    FreeRun,
    FreeRunState,
    check_confidence,
    check_state,
    inputs_with_tail,
    next_u_tail,
    start_index,
)


def simulate_mc_baseline(
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
    local: bool = True,
    state: FreeRunState | None = None,
) -> FreeRun:
    """Monte Carlo free-run over ``n_paths`` paths advanced together (see module docstring).

    u: input record (input units, e.g. N or V). y0: optional first ny measured outputs (output
    units) taken as known; otherwise the system starts from rest. ``progress``: optional callable
    ``progress(done_steps, total_steps)``. ``diverge_limit``: peak |y| [output units] beyond which a
    path counts in ``FreeRun.diverged_paths`` (``model.envelope.divergence_limit``); None: not counted.

    Evaluation of eq. 8 (mean) and eq. 9 (latent variance) at the paths' regressors. All paths share
    the input lags, and their output lags lie close together (their spread is the band, a small
    fraction of the kernel's lengthscale), so with ``local`` (the default) each step uses a second-order
    model of the mean and of the variance around the paths' mean regressor in the ny output-lag
    coordinates (``gp.local_model``: analytic gradient and Hessian, O(M^2 ny) per step instead of
    O(P M^2)), and checks it against eq. 8-9 evaluated exactly at ``LOCAL_CHECKS`` paths (the
    farthest from the mean regressor, where the model's error is largest, and random ones). When the
    check fails (mean error above ``LOCAL_TOL_MEAN`` predictive std or latent-variance error above
    ``LOCAL_TOL_VAR`` of the predictive variance), the farthest 1/16 of the paths, then the farthest
    quarter, is evaluated exactly and the model, checked again on the others, serves the rest;
    failing that, the step is exact at every path (``LOCAL_EXACT_SHARE``). A failed level is skipped
    for the next ``LOCAL_BACKOFF`` steps. Steps with a
    clipped lag, runs with fewer than ``LOCAL_MIN_PATHS`` paths and posteriors ``gp.has_local_model`` refuses
    are exact. ``FreeRun.local_steps`` counts the steps served (wholly or partly) by the local model.
    The random draws are the same as the exact evaluation's (same seed, same paths up to the model's
    error). ``local=False``: every step exact (``freerun_reference.simulate_mc_reference``'s arithmetic).
    ``latent``: also the latent band (``FreeRun.latent_lower``/``latent_upper``; see module docstring).
    ``state``: a ``FreeRunState`` of an earlier run (its ``FreeRun.state``) to continue from, instead of
    starting at rest or at ``y0``: the same paths, random generator and local-model schedule, so a
    record run in chunks gives the numbers of the record run whole. ``FreeRun.state`` is where this
    run ended.
    """
    st = McPathsBaseline(posterior, x_scaler, y_scaler, ny, nu, u, n_paths, seed, y0, confidence, include_noise,
                 keep_paths, latent, state)
    P, n, i0, y0v, noise = st.P, st.n, st.i0, st.y0v, st.noise
    xm, xs, Xs, Ulag, ylag_raw = st.xm, st.xs, st.Xs, st.Ulag, st.ylag_raw
    use_local = (bool(local) and P >= LOCAL_MIN_PATHS
                 and has_local_model(posterior))
    n_check = min(LOCAL_CHECKS, P)
    check_rng = np.random.default_rng(None if seed is None else [int(seed), 0x10CA1])
    floor, retry_at = 0, -1  # after a failed check, start at level ``floor`` until step retry_at
    if state is not None:
        check_rng.bit_generator.state = state.check_rng
        floor, retry_at = int(state.floor), int(state.retry_in)
    local_steps = 0
    # a lag value inside (lo, hi) needs no clipping in any column; outside: clip the next ny steps
    lo = float(np.max(xm[:ny] - LAG_CLIP * xs[:ny]))
    hi = float(np.min(xm[:ny] + LAG_CLIP * xs[:ny]))
    clip_until = -1
    if i0 and not (lo < float(y0v.min()) and float(y0v.max()) < hi):
        clip_until = i0 + ny
    if state is not None:  # the steps a carried lag outside (lo, hi) still takes part in (as the whole run)
        for k in range(ny):  # ylag_raw[:, k] is y_{-1-k}: a lag of the steps up to ny - 1 - k
            col = ylag_raw[:, k]
            if not (lo < float(col.min()) and float(col.max()) < hi):
                clip_until = max(clip_until, ny - 1 - k)
    mu = np.empty(P)
    var = np.empty(P)
    tmp = np.empty((P, 2 * ny))
    for i in range(i0, n):
        Y = Xs[:, :ny]
        np.subtract(ylag_raw, xm[:ny], out=Y)
        Y /= xs[:ny]
        Xs[:, ny:] = Ulag[i]
        clipped = i <= clip_until
        if clipped:
            np.clip(Y, -LAG_CLIP, LAG_CLIP, out=Y)  # a diverging path cannot overflow
        done = False
        if use_local and not clipped:
            start = floor if i < retry_at else 0
            for level in range(start, len(LOCAL_EXACT_SHARE)):
                share = LOCAL_EXACT_SHARE[level]
                done = _local_step(posterior, Xs, ny, noise, n_check, check_rng, mu, var, tmp,
                                   P // share if share else 0)
                if done:
                    break
                floor, retry_at = level + 1, i + LOCAL_BACKOFF
            local_steps += done
        if not done:
            mu[:], var[:] = posterior.predict(Xs, float32=float32)
        ysamp = st.draw(i, mu, var)
        if not (lo < float(ysamp.min()) and float(ysamp.max()) < hi):  # also for non-finite samples
            clip_until = i + ny  # some lag of the next ny steps may need clipping
        if progress is not None and (i % 256 == 0 or i == n - 1):
            progress(i + 1, n)
    end = st.end_state(u, state, check_rng, floor, max(retry_at - n, -1))
    return st.result(diverge_limit, local_steps=local_steps, state=end)


def _local_step(posterior, Xs, ny, noise, n_check, rng, mu, var, tmp, n_exact: int = 0) -> bool:
    """Mean and latent variance of every path from ``gp.local_model`` around the paths' mean
    regressor, into mu and var; False (mu, var undefined) when the check against eq. 8-9 fails.

    n_exact: the n_exact paths farthest from the mean regressor are evaluated exactly (eq. 8-9) and
    the model serves the others, checked at the farthest of those and at random ones.
    """
    P = Xs.shape[0]
    xbar = Xs.mean(axis=0)
    d = Xs[:, :ny] - xbar[:ny]
    half = n_check // 2
    r2 = np.einsum("ij,ij->i", d, d)
    order = np.argpartition(r2, [P - n_exact - half, P - n_exact] if n_exact else P - half)
    ex = order[P - n_exact:] if n_exact else order[:0]
    far = order[P - n_exact - half: P - n_exact]
    rand = order[rng.integers(0, P - n_exact, n_check - half)]
    idx = np.concatenate([ex, far, rand])
    m0, gm, Hm, v0, gv, Hv, m_ex, v_ex = local_model_baseline(posterior, xbar, ny, Xs[idx])
    np.dot(d, np.hstack([Hm, Hv]), out=tmp)
    np.einsum("ij,ij->i", tmp[:, :ny], d, out=mu)
    np.einsum("ij,ij->i", tmp[:, ny:], d, out=var)
    mu *= 0.5
    var *= 0.5
    g = d @ np.column_stack([gm, gv])
    mu += g[:, 0]
    var += g[:, 1]
    mu += m0
    var += v0
    c = slice(n_exact, None)  # the checked paths among idx
    pv = v_ex[c] + noise  # predictive variance: what the draws use
    if not (np.all(np.abs(mu[idx[c]] - m_ex[c]) <= LOCAL_TOL_MEAN * np.sqrt(pv))
            and np.all(np.abs(var[idx[c]] - v_ex[c]) <= LOCAL_TOL_VAR * pv)):
        return False
    np.maximum(var, 1e-300, out=var)
    if n_exact:
        mu[ex] = m_ex[:n_exact]
        var[ex] = v_ex[:n_exact]
    return True


def local_model_baseline(post, x: np.ndarray, ny: int, Xc: np.ndarray | None = None):
    """Second-order model of the predictive mean (eq. 8) and latent variance (eq. 9) around one
    regressor x in its first ``ny`` coordinates (the lagged outputs).

    mean(x + d) ~ m0 + gm . d + d^T Hm d / 2 and var(x + d) ~ v0 + gv . d + d^T Hv d / 2 for d zero
    beyond ny. The variance is expanded as a whole, k(x, x) - |F k(x)|^2 with F the posterior's
    factor (G, or Linv for the exact posterior): q = |F k|^2 has gradient 2 (F J)^T F k and Hessian
    2 (F J)^T (F J) + 2 sum_n (F^T F k)_n d^2 k_n, J = d k / d x[:ny] (``LocalKernel.local_terms``).
    Costs O(M^2 ny) for one point (no per-path work). With ``Xc`` (rows x D), also eq. 8-9 exactly
    at those rows, sharing the one product with F. Returns (m0, gm, Hm, v0, gv, Hv, mean_c, var_c).
    Called once per Monte Carlo step, so the contract is checked once per run by the caller
    (``has_local_model``: a kernel that meets ``LocalKernel``, not a legacy sparse bundle).
    """
    F = post.variance_factor
    if F is None:
        raise NotImplementedError("legacy sparse bundle (no variance factor G)")
    k, J, hess = post.kernel.local_terms(x, post.points, ny)
    kxx, gk, Hk = post.kernel.diag_local(x, ny)
    w = post.mean_weights
    nc = 0 if Xc is None else Xc.shape[0]
    B = np.empty((k.size, 1 + ny + nc))
    B[:, 0] = k
    B[:, 1: 1 + ny] = J
    if nc:
        B[:, 1 + ny:] = post.cross(Xc).T
    mw = w @ B  # k.w, J^T w, Kc w
    FB = F @ B
    Fk, FJ = FB[:, 0], FB[:, 1: 1 + ny]
    m0 = float(mw[0]) + post.mean_shift
    gm = mw[1: 1 + ny]
    Hm = hess(w)
    v0 = kxx - float(Fk @ Fk)
    gv = gk - 2.0 * (FJ.T @ Fk)
    Hv = Hk - 2.0 * (FJ.T @ FJ) - 2.0 * hess(F.T @ Fk)
    mean_c = var_c = None
    if nc:
        mean_c = mw[1 + ny:] + post.mean_shift
        FK = FB[:, 1 + ny:]
        var_c = np.maximum(post.kernel.diag(Xc) - np.einsum("ij,ij->j", FK, FK), 1e-300)
    return m0, gm, Hm, v0, gv, Hv, mean_c, var_c


class McPathsBaseline:
    """The paths of a Monte Carlo free run (section 2.2 step 3) and their band statistics.

    Holds every path's lagged outputs (``ylag_raw``, output units, newest first), the regressor buffer
    ``Xs`` (P, ny + nu) with the standardised input lags ``Ulag`` of each step, and the outputs: mean,
    std, the band's quantiles and the latent band, in output units. ``draw(i, mu, var)`` samples step
    i of every path from N(mu, var + sigma_y^2) (standardised; ``mu``, ``var`` from eqs. 8-9), feeds
    it back and, once a block of steps is full, computes the block's band statistics with one
    vectorised quantile call. ``result`` returns the ``FreeRun``.
    """

    def __init__(self, posterior, x_scaler, y_scaler, ny: int, nu: int, u: np.ndarray, n_paths: int,
                 seed, y0, confidence: float, include_noise: bool, keep_paths: bool, latent: bool,
                 state: FreeRunState | None = None):
        self.t_start = time.perf_counter()
        self.confidence = check_confidence(confidence)
        if int(n_paths) < 1:
            raise ValueError(f"n_paths must be at least 1, got {n_paths}")
        P = self.P = int(n_paths)
        n = self.n = u.size
        self.ny, self.nu = ny, nu
        if state is not None:
            check_state(state, "mc", ny, nu, y0, P)
        self.i0, self.y0v = start_index(n, ny, y0)
        i0, y0v = self.i0, self.y0v
        self.rng = np.random.default_rng(seed)
        if state is not None:
            self.rng.bit_generator.state = state.rng
        self.q = ((1.0 - self.confidence) / 2.0, 1.0 - (1.0 - self.confidence) / 2.0)
        self.mean = np.zeros(n)
        self.std = np.zeros(n)
        self.lower = np.zeros(n)
        self.upper = np.zeros(n)
        if i0:
            self.mean[:i0] = self.lower[:i0] = self.upper[:i0] = y0v
        self.paths = np.zeros((n, P)) if keep_paths else None
        if keep_paths and i0:
            self.paths[:i0] = y0v[:, None]
        self.xm, self.xs = x_scaler.mean_, x_scaler.scale_
        self.ym, self.ys = float(y_scaler.mean_[0]), float(y_scaler.scale_[0])
        self.Ulag = (inputs_with_tail(u, nu, state) - self.xm[ny:]) / self.xs[ny:]  # standardised, shared
        # lagged outputs of every path in output units; at rest = 0
        self.ylag_raw = np.zeros((P, ny))
        if i0:
            self.ylag_raw[:] = y0v[::-1][None, :]  # [y_{i0-1}, ..., y_{i0-ny}]
        elif state is not None:
            self.ylag_raw[:] = state.paths
        self.Xs = np.empty((P, ny + nu))
        self.noise = posterior.noise_var if include_noise else 0.0
        # samples of a block of steps; band statistics are computed per block (one vectorised
        # quantile call per block instead of one per step)
        self.block = max(1, min(256, (1 << 22) // P))
        self.buf = np.empty((self.block, P))
        self.latent = latent
        self.lat = latent and self.noise > 0.0  # without the noise term the latent band is the predictive band
        self.lbuf = np.empty((self.block, P)) if self.lat else None
        self.lat_lo = self.lower.copy() if self.lat else None
        self.lat_hi = self.upper.copy() if self.lat else None
        self.path_peak = np.zeros(P) if state is None else np.array(state.path_peak, dtype=float)  # output units
        self.b0 = i0

    def draw(self, i: int, mu: np.ndarray, var: np.ndarray) -> np.ndarray:
        """Sample step i of every path, feed it back and return the samples (output units)."""
        sd = np.sqrt(var + self.noise)
        ysamp = self.buf[i - self.b0]
        np.multiply(sd, self.rng.standard_normal(self.P), out=ysamp)
        if self.lat:  # latent draw mu + sigma_f eps with the output draw's eps: f = mu + (y - mu) sigma_f / sd
            fsamp = self.lbuf[i - self.b0]
            np.multiply(ysamp, np.sqrt(var) / sd, out=fsamp)
            fsamp += mu
        ysamp += mu
        ysamp *= self.ys
        ysamp += self.ym  # back to output units
        self.mean[i] = float(np.mean(mu)) * self.ys + self.ym
        if self.paths is not None:
            self.paths[i] = ysamp
        self.ylag_raw[:, 1:] = self.ylag_raw[:, :-1]
        self.ylag_raw[:, 0] = ysamp
        if i - self.b0 + 1 == self.block or i == self.n - 1:
            self._statistics(i)
        return ysamp

    def _statistics(self, i: int) -> None:
        b0, ys, ym = self.b0, self.ys, self.ym
        chunk = self.buf[: i - b0 + 1]
        np.maximum(self.path_peak, np.max(np.abs(chunk), axis=0), out=self.path_peak)
        self.std[b0 : i + 1] = np.std(chunk, axis=1)
        self.lower[b0 : i + 1], self.upper[b0 : i + 1] = np.quantile(chunk, self.q, axis=1)
        if self.lat:
            self.lat_lo[b0 : i + 1], self.lat_hi[b0 : i + 1] = np.quantile(self.lbuf[: i - b0 + 1], self.q, axis=1)
            self.lat_lo[b0 : i + 1] *= ys
            self.lat_lo[b0 : i + 1] += ym
            self.lat_hi[b0 : i + 1] *= ys
            self.lat_hi[b0 : i + 1] += ym
        self.b0 = i + 1

    def end_state(self, u: np.ndarray, prev: FreeRunState | None, check_rng, floor: int,
                  retry_in: int) -> FreeRunState:
        """The state after this run's last step (``FreeRunState``), to continue the stream."""
        return FreeRunState("mc", (0 if prev is None else prev.position) + self.n, next_u_tail(u, self.nu, prev),
                            paths=self.ylag_raw.copy(), path_peak=self.path_peak.copy(),
                            rng=self.rng.bit_generator.state, check_rng=check_rng.bit_generator.state,
                            floor=int(floor), retry_in=int(retry_in))

    def result(self, diverge_limit: float | None, **extra) -> FreeRun:
        """The run as a ``FreeRun``; paths whose peak |y| passed ``diverge_limit`` are counted."""
        diverged = 0 if diverge_limit is None else int(np.count_nonzero(~(self.path_peak <= diverge_limit)))
        lat_lo, lat_hi = self.lat_lo, self.lat_hi
        if self.latent and not self.lat:
            lat_lo, lat_hi = self.lower.copy(), self.upper.copy()
        return FreeRun(self.mean, self.std, self.lower, self.upper, self.confidence, self.P, "mc",
                       time.perf_counter() - self.t_start, (self.n - self.i0) * self.P, self.paths, diverged,
                       latent_lower=lat_lo, latent_upper=lat_hi, **extra)
