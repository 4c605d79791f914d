"""What every free run shares: its result type (``FreeRun``, arrays in output units), the clip that keeps
a diverging path finite, and the lagged-input matrix and start index of a record (section 2.2 step 3)."""
from __future__ import annotations

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

    @property
    def band_width(self) -> np.ndarray:
        return self.upper - self.lower


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
