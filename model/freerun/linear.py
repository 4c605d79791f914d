"""Free-run (model predicted output, infinite-step-ahead) prediction with uncertainty propagation.

Section 2.2 step 3 of the paper: each predicted output is a Gaussian random variable fed back as a
lagged regressor. Two propagation methods:

* ``simulate_mc``: Monte Carlo. n paths advance together; at each step every path gets its mean
  (eq. 8) and latent variance (eq. 9), samples y ~ N(mu, sigma^2) and feeds it back. Seeded. By
  default eq. 8-9 come from a second-order local model around the paths' mean regressor, checked
  each step against eq. 8-9 at the farthest paths (exact fallback); ``freerun_reference.simulate_mc_reference``
  evaluates them at every path (one kernel block K(x_paths, X) and one BLAS-3 variance product).
* ``simulate_linear``: first-order (Taylor) propagation of mean and covariance of the lagged
  outputs through the GP mean's Jacobian: var(y_i) = sigma_f^2(x_i) + sigma_y^2 + J S J^T (mean
  recursion, then eq. 9 and J batched over the record, then the covariance recursion;
  ``freerun_reference.simulate_linear_reference`` is the one-call-per-step loop).

Both return a ``FreeRun`` with mean, std and the two-sided band at ``confidence`` (99% default:
the 0.5% and 99.5% quantiles over Monte Carlo paths; mean -/+ 2.576 std for the linearised method).
That predictive band holds the measured output y (noise sigma_y^2 included). ``latent_lower`` and
``latent_upper`` hold the latent band of the noise-free output f at the same confidence: the
reporting step's noise term is left out (Monte Carlo: each path's latent draw mu + sigma_f eps with
the same eps as its output draw, so the paths fed back are unchanged; linearised: var(y_i) without
sigma_y^2). Score y against the predictive band and a noise-free output against the latent band.
All arrays are in the record's output units (e.g. m or m/s).
"""
from __future__ import annotations

import math
import queue
import threading
import time

import numpy as np

from ..kernels import LinearisableKernel, require
from ..linalg import two_cpus
from ..normal import band_z
from ..posterior import Posterior
from .mc_local import LocalModel, has_local_model
from .reference import simulate_linear_reference
from .results import (
    LAG_CLIP,
    VAR_CAP,
    FreeRun,
    FreeRunState,
    McPaths,
    check_confidence,
    check_state,
    inputs_with_tail,
    next_u_tail,
    start_index,
)

# Tolerances of the local model's check (``simulate_mc``), at the checked paths (the farthest from the
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


def simulate_mc(
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
    coordinates (``gp.LocalModel``, ``gp.local_model``'s numbers: analytic gradient and Hessian, O(M^2 ny)
    per step instead of O(P M^2); every path's mean and variance from one (P x (ny + 1)) product), and
    checks it against eq. 8-9 evaluated exactly at ``LOCAL_CHECKS`` paths (the farthest from the mean
    regressor, where the model's error is largest, and random ones). When the
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
    st = McPaths(posterior, x_scaler, y_scaler, ny, nu, u, n_paths, seed, y0, confidence, include_noise,
                 keep_paths, latent, state)
    P, n, i0, y0v = st.P, st.n, st.i0, st.y0v
    xm, xs, Xs, Ulag, ylag_raw = st.xm, st.xs, st.Xs, st.Ulag, st.ylag_raw  # ylag_raw: as it starts
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
    step = _LocalStep(posterior, st, n_check, check_rng) if use_local else None
    for i in range(i0, n):
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
    return st.result(diverge_limit, local_steps=local_steps, state=end)


class _LocalStep:
    """One step of every path from ``gp.LocalModel`` around the paths' mean regressor, checked against
    eq. 8-9 (``simulate_mc``). The regressor deviations d of the paths (P x ny, standardised) come from
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


def simulate_linear(
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
    state: FreeRunState | None = None,
    workers: int | None = None,
) -> FreeRun:
    """First-order (linearised) propagation of mean and covariance through the lagged outputs.

    State: mean m and covariance S (ny x ny) of [y_{i-1}, ..., y_{i-ny}] (output units). With
    J = d mu / d y_lags at the mean regressor (chain rule through the standardisation):
    var(y_i) = sigma_f^2 + sigma_y^2 + J S J^T, cov(y_i, y_{i-k}) = (S J^T)_k; the state shifts.

    cov_window: when L = cov_window > ny, the covariance state covers the last L outputs (J is
    zero beyond the ny lags, so mean and std are unchanged) and ``FreeRun.cov_band`` holds
    cov(y_i, y_{i-k}) for k < L, shape (n, L): what a linear functional of a window of outputs
    (e.g. a cycle's energy, ``model.cycles``) needs for its variance.

    Three passes, the same numbers as one ``mean_grad`` call per step (``freerun_reference.simulate_linear_reference``):
    1. the mean recursion alone (eq. 8 at the mean regressor): it does not depend on the variances,
       and one step is a few numpy calls on (M,) vectors (``_MeanRecursion``);
    2. sigma_f^2 (eq. 9) and J at every mean regressor of the record in row blocks (BLAS-3, the
       posterior's ``mean_var_grad``), each chunk of pass 1's steps as soon as pass 1 has finished it:
       with ``workers`` threads (default: one where this process may use two or more CPUs, none
       otherwise; 0: none) while pass 1 goes on, the rest by the calling thread too once pass 1 ends
       (BLAS without the GIL, ``gp.lower_times_rows``). Same rows, same blocks: the same numbers, bit
       for bit, with any number of workers;
    3. the covariance recursion (ny x ny per step), chunk by chunk in order as pass 2 finishes them, on the
       calling thread once pass 1 has ended (between its own pass-2 chunks), so that it overlaps the
       worker's pass 2 instead of following it.
    Anything else than a ``posterior.Posterior`` whose kernel gives ``MeanTerms`` (e.g. an object with
    only ``mean_grad`` and ``noise_var``) takes the reference loop.

    state: a ``FreeRunState`` of an earlier run (its ``FreeRun.state``) to continue from instead of
    starting at rest or at ``y0``: its last means, input lags and state covariance, so a record run in
    chunks gives the numbers of the record run whole (to round-off). A state with a smaller covariance
    window than ``cov_window`` is padded with zeros (the older covariances start unknown-as-zero); a
    larger one is cut. ``FreeRun.state`` is where this run ended.
    """
    fast = _MeanRecursion.build(posterior, x_scaler, ny, nu)
    if workers is not None and int(workers) < 0:
        raise ValueError(f"workers must be >= 0 (0: no worker thread), got {workers}")
    if state is not None:
        check_state(state, "linear", ny, nu, y0)
        if fast is None:
            raise ValueError("state: this posterior's linearised run cannot continue a stream")
    if fast is None:
        return simulate_linear_reference(posterior, x_scaler, y_scaler, ny, nu, u, y0=y0, confidence=confidence,
                                          include_noise=include_noise, progress=progress, cov_window=cov_window)
    t_start = time.perf_counter()
    confidence = check_confidence(confidence)
    z = band_z(confidence)
    u = np.asarray(u, dtype=float)
    n = u.size
    i0, y0v = start_index(n, ny, y0)
    xm, xs = x_scaler.mean_, x_scaler.scale_
    ym, ys = float(y_scaler.mean_[0]), float(y_scaler.scale_[0])
    Ulag = (inputs_with_tail(u, nu, state) - xm[ny:]) / xs[ny:]
    # pass 1: hist[t + ny] = mean output at time t (output units); hist[:ny] = 0 (at rest) or the state's means
    hist = np.zeros(n + ny)
    if i0:
        hist[ny: 2 * ny] = y0v
    elif state is not None:
        hist[:ny] = state.mean_tail
    # pass 2 of the steps k0 <= i - i0 < k1, once pass 1 has finished them: the mean regressors
    # (standardised, clipped as in pass 1), sigma_f^2 and the mean's gradient, in rows of X blocked from
    # i0 as ``mean_var_grad`` blocks them (so any split in multiples of the chunk gives the same numbers)
    rows = max(n - i0, 0)
    X = np.empty((rows, ny + nu))
    var_f = np.empty(rows)
    grad = np.empty((rows, ny + nu))
    win = np.lib.stride_tricks.sliding_window_view(hist, ny)[:, ::-1]  # row i: [y_{i-1}, ..., y_{i-ny}]

    def pass2(k0: int, k1: int) -> None:
        Xb = X[k0:k1]
        np.subtract(win[i0 + k0: i0 + k1], xm[:ny], out=Xb[:, :ny])
        Xb[:, :ny] /= xs[:ny]
        np.clip(Xb[:, :ny], -LAG_CLIP, LAG_CLIP, out=Xb[:, :ny])
        Xb[:, ny:] = Ulag[i0 + k0: i0 + k1]
        _, var_f[k0:k1], grad[k0:k1] = posterior.mean_var_grad(Xb)

    L = max(ny, int(cov_window or 0))
    band = np.zeros((n, L)) if L > ny else None
    S_end = None if state is None else _resize(np.asarray(state.cov, dtype=float), L)
    noise = posterior.noise_var if include_noise else 0.0
    q = np.empty(rows)  # sigma_f^2 + sigma_y^2 in output units
    Jall = np.empty((rows, ny))  # d mu_out / d y_lag (output units)
    cov = _CovarianceRecursion(rows, ny, L, ys, band, i0, S_end)

    def pass3(k0: int, k1: int) -> None:
        np.add(var_f[k0:k1], noise, out=q[k0:k1])
        q[k0:k1] *= ys * ys
        np.multiply(grad[k0:k1, :ny], ys / xs[:ny], out=Jall[k0:k1])
        cov.advance(q[k0:k1], Jall[k0:k1])

    with _Workers(pass2, _linear_workers(workers, rows, _PASS1_CHUNK), then=pass3) as pool:
        fast.run(hist, Ulag, i0, n, ym, ys, progress, chunk=_PASS1_CHUNK,
                 on_chunk=lambda c0, c1: pool.submit(c0 - i0, c1 - i0))
    mean = hist[ny:].copy()
    std = np.zeros(n)
    lstd = np.zeros(n)  # latent std: var(y_i) without the reporting step's sigma_y^2
    if n > i0:
        var_y, prop, S_end = cov.out, cov.prop, cov.state()
        std[i0:] = np.sqrt(np.maximum(var_y, 0.0))
        # latent: var(y_i) without the reporting step's sigma_y^2 (as the reference loop)
        var_lat = var_f * (ys * ys) + prop
        ok = np.isfinite(var_lat)
        lstd[i0:] = np.where(ok, np.sqrt(np.maximum(np.minimum(np.where(ok, var_lat, 0.0), var_y), 0.0)),
                             std[i0:])
    if progress is not None:
        progress(n, n)
    end = FreeRunState("linear", (0 if state is None else state.position) + n, next_u_tail(u, nu, state),
                       mean_tail=hist[n: n + ny].copy(), cov=np.zeros((L, L)) if S_end is None else S_end)
    return FreeRun(mean, std, mean - z * std, mean + z * std, confidence, 0, "linear",
                   time.perf_counter() - t_start, n - i0, cov_band=band,
                   latent_lower=mean - z * lstd, latent_upper=mean + z * lstd, state=end)


_PASS1_CHUNK = 1024  # steps of pass 1 per chunk: pass 2's unit of work (a multiple of mean_var_grad's block)


def _linear_workers(workers: int | None, rows: int, chunk: int) -> int:
    """Worker threads for pass 2 of ``simulate_linear``: ``workers`` when given, else one where this
    process may run on two or more CPUs and the run has more than one chunk; none otherwise."""
    if workers is not None:
        return int(workers)
    return 1 if rows > chunk and two_cpus() else 0


class _Workers:
    """Runs ``fn(*task)`` for every submitted task: on ``n`` worker threads while the caller goes on,
    and, on leaving the ``with`` block, on the calling thread too until none is left (n = 0: at once,
    on the caller). ``then(*task)``, when given, runs on the calling thread for every task after ``fn`` has
    finished it, in the order the tasks were submitted: on leaving the block, between the caller's own
    tasks (n = 0: right after ``fn``). The first error a task raises is raised on leaving the block."""

    def __init__(self, fn, n: int, then=None):
        self.fn, self.n, self.then = fn, int(n), then
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        self.errors: list[BaseException] = []
        self.order: list[tuple] = []  # submitted tasks, in order
        self.finished: set[tuple] = set()  # tasks fn has finished
        self.cond = threading.Condition()
        self.threads = [threading.Thread(target=self._work, daemon=True, name=f"gpnarx-pass2-{k}")
                        for k in range(self.n)]

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def submit(self, *task) -> None:
        if self.n:
            self.order.append(task)
            self.tasks.put(task)
        else:
            self.fn(*task)
            if self.then is not None:
                self.then(*task)

    def _work(self) -> None:
        while True:
            task = self.tasks.get()
            if task is None:
                return
            self._run(task)

    def _run(self, task) -> None:
        if self.errors:
            return
        try:
            self.fn(*task)
        except BaseException as e:  # raised again on the calling thread
            self.errors.append(e)
        with self.cond:
            self.finished.add(task)
            self.cond.notify_all()

    def __exit__(self, exc_type, exc, tb):
        if self.n:
            try:
                if exc_type is None:
                    self._drain()
            finally:  # also when ``then`` raises: the workers stop
                while True:  # what is left after an error: dropped
                    try:
                        self.tasks.get_nowait()
                    except queue.Empty:
                        break
                for _ in self.threads:
                    self.tasks.put(None)
                for t in self.threads:
                    t.join()
        if exc_type is None and self.errors:
            raise self.errors[0]
        return False

    def _drain(self) -> None:
        """The calling thread: ``then`` for each finished task in order, else a queued task, else waits for a
        worker, until every task is done and followed (or one failed)."""
        done = 0  # tasks followed by ``then``
        while not self.errors:
            while done < len(self.order) and self.order[done] in self.finished:
                if self.then is not None:
                    self.then(*self.order[done])
                done += 1
            try:
                task = self.tasks.get_nowait()
            except queue.Empty:
                if done == len(self.order):
                    return
                want = self.order[done]
                with self.cond:
                    self.cond.wait_for(lambda want=want: want in self.finished or bool(self.errors))
                continue
            self._run(task)


def _resize(S: np.ndarray, L: int) -> np.ndarray:
    """A state covariance as L x L: cut, or padded with zeros (square, symmetric input)."""
    if S.ndim != 2 or S.shape[0] != S.shape[1] or not np.all(np.isfinite(S)):
        raise ValueError("state: cov must be a finite square matrix")
    out = np.zeros((L, L))
    k = min(L, S.shape[0])
    out[:k, :k] = S[:k, :k]
    return out


class _CovarianceRecursion:
    """Pass 3 of ``simulate_linear``: var(y_i) for every step of the linearised propagation (``out``) and its
    propagated part J S J^T (``prop``), and cov(y_i, y_{i-k}) into ``band``, ``advance``d chunk by chunk in
    order.

    S (L x L, output units) is the covariance of [y_{i-1}, ..., y_{i-L}]; one step is
    SJ = S[:, :ny] J, var_y = q_i + J . SJ[:ny], then S shifts down the diagonal with [var_y, SJ]
    as its new first row and column. The shift costs nothing: S is a moving diagonal window of a
    larger buffer (rebased every ``block`` steps). Same caps as the reference loop. ``S0``: the
    covariance to start from (None: zeros, at rest or at known outputs). ``state()``: S after the steps done.
    """

    block = 512

    def __init__(self, steps: int, ny: int, L: int, ys: float, band, i0: int, S0: np.ndarray | None = None):
        self.ny, self.L, self.band, self.i0 = ny, L, band, i0
        self.cap = VAR_CAP * ys * ys
        self.out = np.empty(steps)
        self.prop = np.empty(steps)
        self.k = 0  # steps done
        self.B = np.zeros((L + self.block, L + self.block))
        self.o = self.block  # S = B[o:o+L, o:o+L]
        if S0 is not None:
            self.B[self.o:self.o + L, self.o:self.o + L] = S0

    def advance(self, q: np.ndarray, Jall: np.ndarray) -> None:
        """The next q.size steps: q = sigma_f^2 + sigma_y^2 and Jall (steps, ny) = d mu / d y_lag of each."""
        ny, L, band, i0, cap = self.ny, self.L, self.band, self.i0, self.cap
        B, o, block, out, prop = self.B, self.o, self.block, self.out, self.prop
        isfinite = math.isfinite
        dot = np.dot
        safe = 0.25 * cap
        for j in range(q.size):
            k = self.k + j
            if o == 0:  # rebase: move S to the bottom-right corner
                B[block:, block:] = B[:L, :L]
                o = block
            S = B[o: o + L, o: o + L]
            J = Jall[j]
            SJ = dot(S[:, :ny], J)
            t = float(dot(J, SJ[:ny]))  # J S J^T
            if not (isfinite(t) and -safe < t < safe):
                # the reference loop's guards. Otherwise they change nothing: S is a covariance with
                # diagonal <= cap, so |(S J)_a| <= sqrt(S_aa J S J^T) < cap / 2 (Cauchy-Schwarz)
                if not np.all(np.isfinite(SJ)):  # a diverging run keeps a finite state covariance
                    SJ = np.nan_to_num(SJ, nan=cap, posinf=cap, neginf=-cap)
                np.clip(SJ, -cap, cap, out=SJ)
                t = float(dot(J, SJ[:ny]))
            prop[k] = t
            v = q[j] + t
            v = min(v, cap) if isfinite(v) else cap
            out[k] = v
            o -= 1
            B[o, o] = v
            B[o, o + 1: o + L] = SJ[:-1]
            B[o + 1: o + L, o] = SJ[:-1]
            if band is not None:
                band[i0 + k, 0] = v
                band[i0 + k, 1:] = SJ[:-1]
        self.o = o
        self.k += q.size

    def state(self) -> np.ndarray:
        """S after the steps done (L x L)."""
        return self.B[self.o: self.o + self.L, self.o: self.o + self.L].copy()


class _MeanRecursion:
    """Pass 1 of ``simulate_linear``: the free-run mean y_i = mu(x_i) (eq. 8) fed back as a lag.

    For a posterior whose kernel gives its share of the mean as ``MeanTerms`` (``LinearisableKernel.
    mean_terms``: Matern32, RBF, CubicPolynomial, White and sums of them), one step is about twenty
    numpy calls on (M,) vectors instead of a general kernel evaluation: g = Z x (the input part Z_u x_u
    of every step of a block is one BLAS-3 product before the block), r^2 = |x|^2 + |z|^2 - 2 g, then
    every profile's row f(r^2) into one (rows x M) buffer F next to g, g^2, g^3, and one product F w;
    the kernel's moments, profile scales and constant turn F w into the mean.
    """
    def __init__(self, Z, terms, w, ny, nu, xm, xs):
        self.Z = Z
        self.w = w
        self.ny, self.nu = ny, nu
        self.xm, self.xs = xm, xs
        self.Zy_rev = np.ascontiguousarray(Z[:, :ny][:, ::-1])  # columns in time order y_{i-ny}..y_{i-1}
        self.Zu = np.ascontiguousarray(Z[:, ny:])
        self.sqZ = np.einsum("ij,ij->i", Z, Z)
        self.xm_rev = np.ascontiguousarray(xm[:ny][::-1])
        self.inv_rev = np.ascontiguousarray(1.0 / xs[:ny][::-1])
        self.const = terms.const
        self.has_moments = terms.moments is not None
        self.moments = terms.moments if self.has_moments else (0.0, 0.0, 0.0)  # coefficients of S1, S2, S3
        self.profiles = terms.profiles  # (scale, fill) per row 3, 4, ... of F
        # F rows: 0 = g, 1 = g^2, 2 = g^3 (filled when the kernel has moments), then one row per profile
        self.n_rows = 3 + len(self.profiles)

    @classmethod
    def build(cls, posterior, x_scaler, ny, nu):
        """A recursion for ``posterior``, or None when it is not a ``posterior.Posterior`` or its kernel
        has no ``MeanTerms``."""
        if not isinstance(posterior, Posterior) or getattr(x_scaler, "mean_", None) is None:
            return None
        require(posterior.kernel, LinearisableKernel, "the linearised free run (freerun.simulate_linear)")
        w = np.asarray(posterior.mean_weights, dtype=float)
        terms = posterior.kernel.mean_terms(w)
        if terms is None:
            return None
        return cls(np.ascontiguousarray(posterior.points, dtype=float), terms, w, ny, nu,
                   np.asarray(x_scaler.mean_, float), np.asarray(x_scaler.scale_, float))

    def run(self, hist, Ulag, i0, n, ym, ys, progress=None, chunk=1024, on_chunk=None):
        """Fill hist[ny + i] with the mean output of every step i0 <= i < n (output units), ``chunk``
        steps at a time; ``on_chunk(c0, c1)`` after the steps c0 <= i < c1 are final."""
        ny = self.ny
        M = self.Z.shape[0]
        F = np.zeros((self.n_rows, M))
        g, g2, g3 = F[0], F[1], F[2]
        gy, gy2 = np.empty(M), np.empty(M)  # Z_y x_y and -2 Z_y x_y (scaling by -2 is exact: the same
        Zy = self.Zy_rev  # numbers as a product with -2 Z_y, at half the matrix's size in cache)
        r = np.empty(M)
        xy = np.empty(ny)
        wv = self.w
        c1, c2, c3 = self.moments
        const = self.const
        has_moments = self.has_moments
        profiles = list(enumerate(self.profiles, start=3))  # (F row, (scale, fill))
        single = len(profiles) == 1
        xm_r, inv_r = self.xm_rev, self.inv_rev
        # conservative range of a lag value whose standardised value needs no clipping (any column)
        lo = float(np.max(self.xm[:ny] - LAG_CLIP * self.xs[:ny]))
        hi = float(np.min(self.xm[:ny] + LAG_CLIP * self.xs[:ny]))
        clip_until = -1
        for k in range(ny):  # initial lags (y0) outside that range
            v = hist[i0 + k]
            if not lo <= v <= hi:
                clip_until = i0 + ny
        dot, multiply, subtract, add = np.dot, np.multiply, np.subtract, np.add
        maximum = np.maximum
        for c0 in range(i0, n, chunk):
            c1_ = min(n, c0 + chunk)
            Uc = Ulag[c0:c1_]
            GU = Uc @ self.Zu.T  # input part of g = Z x for every step of the chunk
            # |z|^2 + |x_u|^2 - 2 Z_u x_u: r^2 = that + |x_y|^2 - 2 Z_y x_y
            R0 = GU * -2.0
            R0 += self.sqZ
            R0 += np.einsum("ij,ij->i", Uc, Uc)[:, None]
            for i in range(c0, c1_):
                j = i - c0
                subtract(hist[i: i + ny], xm_r, out=xy)
                xy *= inv_r
                if i <= clip_until:
                    np.clip(xy, -LAG_CLIP, LAG_CLIP, out=xy)
                dot(Zy, xy, out=gy)
                add(gy, GU[j], out=g)
                if profiles:
                    multiply(gy, -2.0, out=gy2)
                    add(gy2, R0[j], out=r)
                    r += float(dot(xy, xy))
                    maximum(r, 0.0, out=r)
                    for row, (_, fill) in profiles:
                        fill(r if single else r.copy(), F[row])
                if has_moments:
                    multiply(g, g, out=g2)
                    multiply(g2, g, out=g3)
                vals = dot(F, wv)
                mu = const + c1 * vals[0] + c2 * vals[1] + c3 * vals[2]
                for row, (scale, _) in profiles:
                    mu += scale * vals[row]
                y = mu * ys + ym
                hist[ny + i] = y
                if not lo <= y <= hi:
                    clip_until = i + ny
                if progress is not None and (i % 4096 == 0):
                    progress(i + 1, n)
            if on_chunk is not None:
                on_chunk(c0, c1_)
