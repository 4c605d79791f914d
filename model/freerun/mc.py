"""The Monte Carlo free run on numpy (section 2.2 step 3): P paths advance together; at each step every path
gets its mean (eq. 8) and latent variance (eq. 9), samples y ~ N(mu, sigma_f^2 + sigma_y^2) and feeds it back.
Seeded. The band: the paths' quantiles at the run's confidence; the latent band: each path's latent draw
mu + sigma_f eps with its output draw's eps (so the paths fed back are unchanged).

Eq. 8-9 at every path cost O(P M^2) a step. The paths share their input lags and their output lags lie close
together (their spread is the band, a small fraction of the kernel's lengthscale), so by default a step takes a
second-order model of eq. 8-9 around the paths' mean regressor in the ny output-lag coordinates
(``mc_local.LocalModel``: O(M^2 ny), then every path's mean and variance from one (P x (ny + 1)) product),
checked against eq. 8-9 at ``LOCAL_CHECKS`` paths: the farthest from the mean regressor, where its error is
largest, and random ones. A failed check evaluates the farthest 1/16, then 1/4, then all of the paths exactly
(``LOCAL_EXACT_SHARE``), and a failed level is skipped for ``LOCAL_BACKOFF`` steps. Steps with a clipped lag,
runs of fewer than ``LOCAL_MIN_PATHS`` paths and posteriors ``mc_local.has_local_model`` refuses are exact. The
draws are the exact evaluation's (same seed: the same paths up to the model's error).
"""
from __future__ import annotations

import numpy as np

from .mc_local import LocalModel, has_local_model
from .mc_paths import McPaths
from .results import FreeRun
from .spec import LAG_CLIP, Predictor, RunSpec

# Tolerances of the local model's check (``run_mc``), at the checked paths (the farthest from the
# mean regressor: the model's error grows as |d|^3, so these bound it for all paths). The 0.5 % and
# 99.5 % quantiles of P paths carry a Monte Carlo standard error of sqrt(q (1 - q) / P) / phi(z_q),
# 0.15 predictive std at P = 1024 and 0.075 at 4096: a mean error of 5e-3 std at the band's own
# paths is 15-30x below it; a latent-variance error of 1 % moves a std by 0.5 %.
LOCAL_TOL_MEAN = 5e-3  # largest mean error allowed, in predictive std
LOCAL_TOL_VAR = 1e-2  # largest latent-variance error, relative to the predictive variance
LOCAL_CHECKS = 12  # paths checked against eq. 8-9 per step: the farthest from the mean regressor, and random ones
LOCAL_MIN_PATHS = 64  # fewer paths: every step exact
LOCAL_BACKOFF = 16  # steps that start at the next level after a failed check
LOCAL_EXACT_SHARE = (0, 16, 4)  # levels: exact at none, at the farthest 1/16, 1/4 of the paths; then all exact


def run_mc(predictor: Predictor, u: np.ndarray, spec: RunSpec, restarts: dict | None = None) -> FreeRun:
    """Monte Carlo free run over ``spec.n_paths`` paths of input ``u`` (input units); see the module docstring.

    ``spec.local`` False: every step exact (``reference.simulate_mc_reference``'s numbers). ``spec.state``: the
    ``FreeRun.state`` of an earlier run to continue: the same paths, generators and local-model schedule, so a
    record run in chunks gives the numbers of the record run whole. ``FreeRun.local_steps`` counts the steps the
    local model served (wholly or partly); ``FreeRun.diverged_paths`` the paths past ``predictor.diverge_limit``.
    ``restarts``: {sample i: its ny output lags [y_{i-1}, ..., y_{i-ny}] (output units)}: before step i every
    path's lags are set to them (a k-step prediction's restart from measured outputs, ``horizon``).
    """
    posterior, ny = predictor.posterior, predictor.ny
    seed, state, progress, float32 = spec.seed, spec.state, spec.progress, spec.float32
    st = McPaths(predictor, u, spec)
    P, n, i0, y0v = st.P, st.n, st.i0, st.y0v
    xm, xs, Xs, Ulag, ylag_raw = st.xm, st.xs, st.Xs, st.Ulag, st.ylag_raw  # ylag_raw: as it starts
    use_local = bool(spec.local) and P >= LOCAL_MIN_PATHS and has_local_model(posterior)
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
    step = _LocalStep(posterior, st, n_check, check_rng) if use_local else None
    for i in range(i0, n):
        if restarts and i in restarts:
            lags = restarts[i]
            st.restart(lags)
            if not (lo < float(lags.min()) and float(lags.max()) < hi):
                clip_until = max(clip_until, i + ny - 1)
        clipped = i <= clip_until
        done = False
        if use_local and not clipped:
            start = floor if i < retry_at else 0
            for level in range(start, len(LOCAL_EXACT_SHARE)):
                share = LOCAL_EXACT_SHARE[level]
                done = step(i, mu, var, P // share if share else 0)
                if done:
                    break
                floor, retry_at = level + 1, i + LOCAL_BACKOFF
            local_steps += done
        if not done:
            Y = Xs[:, :ny]
            np.subtract(st.ylag_raw, xm[:ny], out=Y)
            Y /= xs[:ny]
            Xs[:, ny:] = Ulag[i]
            if clipped:
                np.clip(Y, -LAG_CLIP, LAG_CLIP, out=Y)  # a diverging path cannot overflow
            mu[:], var[:] = posterior.predict(Xs, float32=float32)
        ysamp = st.draw(i, mu, var)
        if not (lo < float(ysamp.min()) and float(ysamp.max()) < hi):  # also for non-finite samples
            clip_until = i + ny  # some lag of the next ny steps may need clipping
        if progress is not None and (i % 256 == 0 or i == n - 1):
            progress(i + 1, n)
    end = st.end_state(u, state, check_rng, floor, max(retry_at - n, -1))
    return st.result(predictor.diverge_limit, local_steps=local_steps, state=end)


def simulate_mc(posterior, x_scaler, y_scaler, ny: int, nu: int, u: np.ndarray, *,
                diverge_limit: float | None = None, **options) -> FreeRun:
    """``run_mc`` from a posterior, its scalers and lags (``Predictor.of``) with the ``RunSpec`` fields as keywords."""
    return run_mc(Predictor.of(posterior, x_scaler, y_scaler, ny, nu, diverge_limit), u,
                  RunSpec(method="mc", **options))


class _LocalStep:
    """One step of every path from ``mc_local.LocalModel`` around the paths' mean regressor, checked against
    eq. 8-9 (``run_mc``). The regressor deviations d of the paths (P x ny, standardised) come from
    the raw lags and their means over the paths (``McPaths.lag_means``), in a (P x (ny + 1)) buffer
    whose last column is 1, so that the mean and the latent variance of every path are one product
    with the model's augmented matrices and two row sums.
    """

    def __init__(self, posterior, st, n_check, rng):
        ny, P = st.ny, st.P
        self.st, self.ny, self.n_check, self.rng = st, ny, n_check, rng
        self.model = LocalModel(posterior, ny)
        self.noise = st.noise
        self.xm, self.xs = st.xm[:ny], st.xs[:ny]
        self.inv_xs = (1.0 / self.xs)[:, None]
        self.d_t = np.empty((ny, P))  # d by rows: the elementwise work on contiguous rows of P
        self.daug = np.ones((P, ny + 1))  # [d, 1]: the product's operand
        self.T = np.empty((P, 2 * (ny + 1)))
        self.r2 = np.empty(P)
        self.x = np.empty(st.Xs.shape[1])

    def __call__(self, i: int, mu: np.ndarray, var: np.ndarray, n_exact: int = 0) -> bool:
        """Mean and latent variance of every path into mu and var; False (mu, var undefined) when the
        check against eq. 8-9 fails. n_exact: the n_exact paths farthest from the mean regressor are
        evaluated exactly (eq. 8-9) and the model serves the others, checked at the farthest of those
        and at random ones.
        """
        st, ny, n_check = self.st, self.ny, self.n_check
        P = st.P
        Wt, ybar, u = st.lags_t, st.lag_means, st.Ulag[i]
        x = self.x
        np.subtract(ybar, self.xm, out=x[:ny])
        x[:ny] /= self.xs
        x[ny:] = u
        d_t = np.subtract(Wt, ybar[:, None], out=self.d_t)
        d_t *= self.inv_xs
        r2 = np.einsum("ji,ji->i", d_t, d_t, out=self.r2)
        half = n_check // 2
        order = np.argpartition(r2, [P - n_exact - half, P - n_exact] if n_exact else P - half)
        ex = order[P - n_exact:] if n_exact else order[:0]
        far = order[P - n_exact - half: P - n_exact]
        rand = order[self.rng.integers(0, P - n_exact, n_check - half)]
        idx = np.concatenate([ex, far, rand])
        Xc = np.empty((idx.size, x.size))
        np.subtract(Wt[:, idx].T, self.xm, out=Xc[:, :ny])
        Xc[:, :ny] /= self.xs
        Xc[:, ny:] = u
        H, m_ex, v_ex = self.model(x, Xc)
        a = ny + 1
        # the check first, at the checked paths only
        dc = np.ones((idx.size - n_exact, a))
        dc[:, :ny] = d_t[:, idx[n_exact:]].T
        Tc = dc @ H
        pv = v_ex[n_exact:] + self.noise  # predictive variance: what the draws use
        if not (np.all(np.abs(np.einsum("ij,ij->i", Tc[:, :a], dc) - m_ex[n_exact:]) <= LOCAL_TOL_MEAN * np.sqrt(pv))
                and np.all(np.abs(np.einsum("ij,ij->i", Tc[:, a:], dc) - v_ex[n_exact:]) <= LOCAL_TOL_VAR * pv)):
            return False
        daug = self.daug
        daug[:, :ny] = d_t.T
        T = np.dot(daug, H, out=self.T)
        np.einsum("ij,ij->i", T[:, :a], daug, out=mu)
        np.einsum("ij,ij->i", T[:, a:], daug, out=var)
        np.maximum(var, 1e-300, out=var)
        if n_exact:
            mu[ex] = m_ex[:n_exact]
            var[ex] = v_ex[:n_exact]
        return True
