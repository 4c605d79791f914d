"""What a free run reads: the fitted model (``Predictor``) and the call (``RunSpec``), and what every run derives
from them: the start index, the lagged inputs and the clip that keeps a diverging path finite."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .results import FreeRunState

LAG_CLIP = 1e3  # standardised lagged outputs are clipped to +/- this (diverging paths stay finite)
VAR_CAP = LAG_CLIP**2  # linearised variance cap (standardised units)


@dataclass(frozen=True, eq=False)
class Predictor:
    """A fitted GP-NARX model as every free run reads it, built once from the model (``GPNARX.predictor()``) or
    from its parts (``Predictor.of``).

    posterior: the GP posterior of eqs. 8-9 (``posterior.Posterior``; the stepwise linearised run needs only its
    ``mean_grad`` and ``noise_var``). x_mean, x_scale: the regressors' standardisation, ny output lags then nu
    input lags; y_mean, y_scale: the output's, in output units. diverge_limit: peak |y| [output units] beyond
    which a Monte Carlo path counts in ``FreeRun.diverged_paths`` (``model.envelope.divergence_limit``; None: not
    counted).
    """

    posterior: Any
    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: float
    y_scale: float
    ny: int
    nu: int
    diverge_limit: float | None = None

    @classmethod
    def of(cls, posterior, x_scaler, y_scaler, ny: int, nu: int, diverge_limit: float | None = None) -> Predictor:
        """From a posterior and the two fitted scalers (anything with ``mean_`` and ``scale_``)."""
        return cls(posterior, x_scaler.mean_, x_scaler.scale_, float(y_scaler.mean_[0]), float(y_scaler.scale_[0]),
                   ny, nu, diverge_limit)

    def noise(self, spec: RunSpec) -> float:
        """sigma_y^2 (standardised) the run's draws and predictive band include: 0 without ``include_noise``."""
        return self.posterior.noise_var if spec.include_noise else 0.0

    def input_lags(self, u: np.ndarray, state: FreeRunState | None = None) -> np.ndarray:
        """The standardised lagged inputs (n, nu) of ``u``; the lags before its first sample from ``state``
        (zeros without one: the system at rest)."""
        ny = self.ny
        return (inputs_with_tail(u, self.nu, state) - self.x_mean[ny:]) / self.x_scale[ny:]


@dataclass(frozen=True, eq=False)
class RunSpec:
    """One free run's options, the same value for every method and backend (each runner reads those it uses).

    method: 'mc' (Monte Carlo) or 'linear' (first-order propagation); backend: 'numpy' or 'jax' (``model.backend``).
    n_paths, seed: Monte Carlo paths and the seed of their draws. confidence: the two-sided band's level. The
    start: ``y0``, the first ny measured outputs (output units) taken as known, or ``state``, a ``FreeRunState``
    of an earlier run to continue (numpy); neither: from rest. include_noise: the draws and the predictive band
    include sigma_y^2. float32: eq. 9's variance product in single precision. keep_paths: every Monte Carlo path
    in ``FreeRun.paths``. latent: also the latent band. local: Monte Carlo on numpy served by the checked local
    model (``mc``). cov_window: linearised, the output covariance over that many lags (``FreeRun.cov_band``).
    workers: linearised on numpy, pass 2's worker threads (None: one where the process may use two CPUs).
    variance_stride: linearised on numpy, eq. 9's latent variance at every s-th step only, linearly interpolated
    between (1: every step, exact; opt-in: the band's difference per real record is in docs/numerics.md).
    progress: ``progress(done_steps, total_steps)``, or None.
    """

    method: str = "mc"
    backend: str = "numpy"
    n_paths: int = 1024
    seed: int | None = 0
    confidence: float = 0.99
    y0: Any = None
    state: FreeRunState | None = None
    include_noise: bool = True
    float32: bool = False
    keep_paths: bool = False
    latent: bool = True
    local: bool = True
    cov_window: int = 0
    workers: int | None = None
    variance_stride: int = 1
    progress: Callable[[int, int], Any] | None = None


def check_confidence(confidence: float) -> float:
    c = float(confidence)
    if not 0.5 <= c < 1.0:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    return c


def check_stride(stride) -> int:
    """A variance stride (``RunSpec.variance_stride``) as a positive int; anything else is refused."""
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or int(stride) < 1:
        raise ValueError(f"variance_stride must be a positive integer, got {stride!r}")
    return int(stride)


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


def lagged_inputs(u: np.ndarray, nu: int) -> np.ndarray:
    """(n, nu) matrix of [u_i, u_{i-1}, ..., u_{i-nu+1}], zeros before the record (system at rest)."""
    n = u.size
    upad = np.concatenate([np.zeros(nu - 1), u])
    cols = [upad[nu - 1 - j : nu - 1 - j + n] for j in range(nu)]
    return np.stack(cols, axis=1)


def inputs_with_tail(u: np.ndarray, nu: int, state: FreeRunState | None) -> np.ndarray:
    """(n, nu) lagged inputs of ``u``; the lags before its first sample come from ``state.u_tail`` (its
    length is checked by ``check_state``)."""
    if state is None:
        return lagged_inputs(u, nu)
    return lagged_inputs(np.concatenate([np.asarray(state.u_tail, dtype=float), u]), nu)[nu - 1:]


def next_u_tail(u: np.ndarray, nu: int, state: FreeRunState | None) -> np.ndarray:
    """The last nu - 1 inputs after ``u`` (with the state's tail when ``u`` is shorter)."""
    prev = np.zeros(nu - 1) if state is None else np.asarray(state.u_tail, dtype=float)
    return np.concatenate([prev, np.asarray(u, dtype=float)])[len(u):] if nu > 1 else np.zeros(0)
