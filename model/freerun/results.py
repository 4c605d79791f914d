"""What a free run returns: ``FreeRun`` (its mean, std and bands, in output units) and where it ended,
``FreeRunState``, which the next chunk of the same record continues from (``check_state``: whether it may)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FreeRun:
    """One free run (output units). mean, std; lower, upper: the two-sided predictive band at ``confidence`` for
    the measured output y (sigma_y^2 included: Monte Carlo, the paths' quantiles; linearised, mean -/+ z std);
    latent_lower, latent_upper: the band of the noise-free output f at the same confidence (the reporting step's
    sigma_y^2 left out; fed-back outputs keep theirs). n_paths: Monte Carlo paths (0: linearised); path_steps:
    the paths times the steps run; seconds: its wall time."""

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
    local_steps: int = 0  # Monte Carlo steps served by the checked local model (``mc.run_mc``)
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
    ``operations.cycle_stream``; ``"novelty"``: the rolling window, ``operations.novelty_window``), each a dict of
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
