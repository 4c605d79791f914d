"""What every free run shares: its result type (``FreeRun``, arrays in output units), the clip that keeps
a diverging path finite, and the lagged-input matrix and start index of a record (section 2.2 step 3)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

LAG_CLIP = 1e3  # standardised lagged outputs are clipped to +/- this (diverging paths stay finite)
VAR_CAP = LAG_CLIP**2  # linearised variance cap (standardised units)


@dataclass
class FreeRun:
    mean: np.ndarray
    std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    confidence: float
    n_paths: int
    method: str
    seconds: float = 0.0
    path_steps: int = 0
    paths: np.ndarray | None = field(default=None, repr=False)
    diverged_paths: int = 0  # Monte Carlo paths whose |y| passed ``diverge_limit`` (see model.envelope)
    cov_band: np.ndarray | None = field(default=None, repr=False)  # linearised cov(y_i, y_{i-k}), (n, L)
    local_steps: int = 0  # Monte Carlo steps evaluated by the checked local model (``simulate_mc``)
    # the latent band: the same confidence for the noise-free output f (no sigma_y^2 term at the step
    # reported; fed-back outputs keep their noise), to score against a noise-free output y_clean
    latent_lower: np.ndarray | None = field(default=None, repr=False)
    latent_upper: np.ndarray | None = field(default=None, repr=False)
    backend: str = "numpy"  # the array backend that ran it (``model.backend``)
    state: "FreeRunState | None" = field(default=None, repr=False)  # where the run ended, to continue it


    @property
    def band_width(self) -> np.ndarray:
        return self.upper - self.lower


@dataclass
class FreeRunState:
    """Where a free run ended: what the next chunk of the same record needs to continue it exactly.

    method: 'linear' or 'mc'. position: samples of the stream consumed so far. u_tail: the last
    nu - 1 inputs (input units; zeros before the stream began). Linearised: ``mean_tail``, the last
    ny mean outputs (output units, oldest first) and ``cov``, the covariance (output units squared)
    of [y_{i-1}, ..., y_{i-L}]. Monte Carlo: ``paths``, every path's last ny outputs (P x ny, newest
    first), ``path_peak`` (running peak |y| of each path), the random generator's state ``rng`` and
    the local model's check generator ``check_rng``, ``floor`` and ``retry_in`` (steps until the
    local model retries its cheapest level). ``amp_tail``: the last mean outputs the band's
    discrepancy window needs on its left (``model.discrepancy``); ``amp_hold``: its held amplitude at the
    last sample (one value; None without a hold). ``carry``: what an operation carries
    across a stream's chunks beside the free run, by operation name (``"loops"``: the unfinished cycle,
    ``model.cycle_stream``; ``"novelty"``: the rolling window, ``model.novelty_window``), each a dict of
    numpy arrays and JSON values.
    """

    method: str
    position: int
    u_tail: np.ndarray
    mean_tail: np.ndarray | None = None
    cov: np.ndarray | None = None
    paths: np.ndarray | None = None
    path_peak: np.ndarray | None = None
    rng: dict | None = None
    check_rng: dict | None = None
    floor: int = 0
    retry_in: int = 0
    amp_tail: np.ndarray | None = None
    amp_hold: np.ndarray | None = None
    carry: dict | None = None


def inputs_with_tail(u: np.ndarray, nu: int, state: "FreeRunState | None") -> np.ndarray:
    """(n, nu) lagged inputs of ``u``; the lags before its first sample come from ``state.u_tail`` (its
    length is checked by ``check_state``)."""
    if state is None:
        return lagged_inputs(u, nu)
    return lagged_inputs(np.concatenate([np.asarray(state.u_tail, dtype=float), u]), nu)[nu - 1:]


def next_u_tail(u: np.ndarray, nu: int, state: "FreeRunState | None") -> np.ndarray:
    """The last nu - 1 inputs after ``u`` (with the state's tail when ``u`` is shorter)."""
    prev = np.zeros(nu - 1) if state is None else np.asarray(state.u_tail, dtype=float)
    return np.concatenate([prev, np.asarray(u, dtype=float)])[len(u):] if nu > 1 else np.zeros(0)


def check_state(state: FreeRunState, method: str, ny: int, nu: int, y0, n_paths: int = 0) -> None:
    """Refuse a state that cannot continue this run (ValueError naming what differs)."""
    if not isinstance(state, FreeRunState):
        raise ValueError(f"state must be a FreeRunState, got {type(state).__name__}")
    if state.method != method:
        raise ValueError(f"state continues a '{state.method}' free run; this call's method is '{method}' "
                         f"(send method '{state.method}')")
    if y0 is not None and np.asarray(y0).size:
        raise ValueError("state: give either y0 (a new start) or a state (a continuation), not both")
    if method == "mc":
        paths = np.asarray(state.paths)
        if paths.shape != (n_paths, ny):
            n_state, n_lags = paths.shape if paths.ndim == 2 else (0, 0)
            raise ValueError(f"state carries {n_state} Monte Carlo paths of {n_lags} lags; this call asks for "
                             f"mc_paths={n_paths} with ny={ny} (send mc_paths={n_state})")
        if state.path_peak is None or np.asarray(state.path_peak).shape != (n_paths,):
            raise ValueError(f"state: path_peak must hold one peak per path ({n_paths})")
        if state.rng is None:
            raise ValueError("state: a Monte Carlo state needs its random generator's state")
    else:
        if np.asarray(state.mean_tail).shape != (ny,):
            raise ValueError(f"state: mean_tail must hold ny={ny} outputs")
        cov = np.asarray(state.cov)
        if cov.ndim != 2 or cov.shape[0] != cov.shape[1] or cov.shape[0] < ny:
            raise ValueError(f"state: cov must be a square matrix of at least ny={ny} lags, got shape {cov.shape}")
    if np.asarray(state.u_tail).shape != (nu - 1,):
        raise ValueError(f"state: u_tail must hold nu - 1 = {nu - 1} inputs")
    for name in ("u_tail", "mean_tail", "cov", "paths", "path_peak", "amp_tail", "amp_hold"):
        v = getattr(state, name)
        if v is not None and not np.all(np.isfinite(np.asarray(v, dtype=float))):
            raise ValueError(f"state: {name} holds a non-finite number")
    if state.amp_hold is not None and np.asarray(state.amp_hold).size != 1:
        raise ValueError("state: amp_hold must hold one number")
    if state.amp_tail is not None and np.asarray(state.amp_tail).ndim != 1:
        raise ValueError("state: amp_tail must be 1-D")


def check_confidence(confidence: float) -> float:
    c = float(confidence)
    if not 0.5 <= c < 1.0:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    return c


def lagged_inputs(u: np.ndarray, nu: int) -> np.ndarray:
    """(n, nu) matrix of [u_i, u_{i-1}, ..., u_{i-nu+1}], zeros before the record (system at rest)."""
    n = u.size
    upad = np.concatenate([np.zeros(nu - 1), u])
    cols = [upad[nu - 1 - j : nu - 1 - j + n] for j in range(nu)]
    return np.stack(cols, axis=1)


def start_index(n: int, ny: int, y0) -> tuple[int, np.ndarray]:
    """Index where free-run starts and the known initial outputs (empty when starting from rest)."""
    if y0 is None:
        return 0, np.zeros(0)
    y0 = np.asarray(y0, dtype=float).ravel()
    if y0.size == 0:
        return 0, y0
    if y0.size < ny:
        raise ValueError(f"y0 must hold at least ny={ny} initial outputs, got {y0.size}")
    if not np.all(np.isfinite(y0)):
        raise ValueError("y0 holds non-finite values")
    y0 = y0[:ny]
    if n <= ny:
        raise ValueError(f"u must be longer than ny={ny} samples when y0 is given, got {n}")
    return ny, y0


class McPaths:
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
        # lagged outputs of every path in output units (at rest = 0), one row per lag: the window
        # ``lags_t`` (ny, P) of a taller buffer that moves one row up per step, so feeding a sample back
        # writes one contiguous row instead of shifting P x ny values (rebased every ``slack`` steps);
        # with each lag's mean over the paths (``lag_means``)
        self.slack = max(64, ny)
        self._lags = np.zeros((ny + self.slack, P))
        self._lag_means = np.zeros(ny + self.slack)
        self._o = self.slack
        if i0:
            self.ylag_raw[:] = y0v[::-1][None, :]  # [y_{i0-1}, ..., y_{i0-ny}]
        elif state is not None:
            self.ylag_raw[:] = state.paths
        for k in range(ny):  # as draw() takes a new sample's mean
            self._lag_means[self._o + k] = np.mean(self._lags[self._o + k])
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

    @property
    def lags_t(self) -> np.ndarray:
        """Every path's last ny outputs as rows (ny, P), newest first (output units): a contiguous view,
        valid until the next draw."""
        return self._lags[self._o: self._o + self.ny]

    @property
    def ylag_raw(self) -> np.ndarray:
        """Every path's last ny outputs (P, ny), newest first (output units): ``lags_t`` transposed."""
        return self.lags_t.T

    @property
    def lag_means(self) -> np.ndarray:
        """The mean over the paths of each column of ``ylag_raw`` (ny,): a view, valid until the next draw."""
        return self._lag_means[self._o: self._o + self.ny]

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
        o = self._o
        if o == 0:  # rebase: the window's newest ny - 1 rows move to the bottom
            S, ny = self.slack, self.ny
            self._lags[S + 1:] = self._lags[: ny - 1]
            self._lag_means[S + 1:] = self._lag_means[: ny - 1]
            o = S + 1
        o -= 1
        self._lags[o] = ysamp
        self._lag_means[o] = np.mean(ysamp)
        self._o = o
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
