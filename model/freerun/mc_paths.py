"""The paths of a Monte Carlo free run (``mc``): every path's lagged outputs, the draws that feed them back and
the band statistics of the steps run."""
from __future__ import annotations

import time

import numpy as np

from .results import FreeRun, FreeRunState, check_state
from .spec import Predictor, RunSpec, check_confidence, next_u_tail, start_index


class McPaths:
    """The paths of a Monte Carlo free run (section 2.2 step 3) and their band statistics.

    Holds every path's lagged outputs (``ylag_raw``, output units, newest first), the regressor buffer
    ``Xs`` (P, ny + nu) with the standardised input lags ``Ulag`` of each step, and the outputs: mean,
    std, the band's quantiles and the latent band, in output units. ``draw(i, mu, var)`` samples step
    i of every path from N(mu, var + sigma_y^2) (standardised; ``mu``, ``var`` from eqs. 8-9), feeds
    it back and, once a block of steps is full, computes the block's band statistics with one
    vectorised quantile call. ``result`` returns the ``FreeRun``.
    """

    def __init__(self, predictor: Predictor, u: np.ndarray, spec: RunSpec):
        self.t_start = time.perf_counter()
        self.confidence = check_confidence(spec.confidence)
        n_paths, y0, state, keep_paths = spec.n_paths, spec.y0, spec.state, spec.keep_paths
        if int(n_paths) < 1:
            raise ValueError(f"n_paths must be at least 1, got {n_paths}")
        P = self.P = int(n_paths)
        n = self.n = u.size
        ny, nu = self.ny, self.nu = predictor.ny, predictor.nu
        if state is not None:
            check_state(state, "mc", ny, nu, y0, P)
        self.i0, self.y0v = start_index(n, ny, y0)
        i0, y0v = self.i0, self.y0v
        self.rng = np.random.default_rng(spec.seed)
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
        self.xm, self.xs = predictor.x_mean, predictor.x_scale
        self.ym, self.ys = predictor.y_mean, predictor.y_scale
        self.Ulag = predictor.input_lags(u, state)  # standardised, shared by all paths
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
        self.noise = predictor.noise(spec)
        # samples of a block of steps; band statistics are computed per block (one vectorised
        # quantile call per block instead of one per step)
        self.block = max(1, min(256, (1 << 22) // P))
        self.buf = np.empty((self.block, P))
        self.latent = latent = spec.latent
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

    def restart(self, lags: np.ndarray) -> None:
        """Set every path's last ny outputs to ``lags`` (ny,), newest first (output units): a restart from measured
        outputs (``horizon``)."""
        self.lags_t[:] = np.asarray(lags, dtype=float)[:, None]
        self.lag_means[:] = lags

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
