"""The posterior contract: what the free runs (``freerun``, ``freerun.jax_backend``), the Monte Carlo local model
(``freerun.mc_local``) and the JAX backend's solves (``ml2_jax``) read of a GP posterior, eqs. (8)-(9).

A posterior writes its mean and latent variance over M points it conditions on (``points``: the
training rows of an exact posterior, the inducing inputs of a sparse one; standardised regressors):

    mean(x)  = K(x, points) w + mean_shift                      (eq. 8, w = ``mean_weights``)
    var_f(x) = k(x, x) - |F K(points, x)|^2                      (eq. 9, F = ``variance_factor``)

``gp.ExactPosterior`` (w = alpha, F = L^-1) and ``gp.SparsePosterior`` (w, F = G) implement it; a
consumer asks these members, never which posterior it holds. All quantities are in standardised
units. ``kind`` and ``arrays`` are what a bundle stores (its ``mode`` and its ``posterior_*`` arrays).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from .kernels import Kernel


@runtime_checkable
class Posterior(Protocol):
    """A GP posterior as the free runs and the local model use it (see the module docstring)."""

    kernel: Kernel  # the kernel of eq. 9's variance (a capped copy, ``Kernel.for_posterior``)
    noise_var: float  # sigma_y^2 (standardised output units squared)
    mean_shift: float  # constant added to K w: the capped constant's share of eq. 8
    kind: str  # the bundle's mode: 'exact' or 'sparse'

    @property
    def points(self) -> np.ndarray:
        """The M points (M, D) the mean and variance are written over."""

    @property
    def n_points(self) -> int:
        """M."""

    @property
    def mean_weights(self) -> np.ndarray:
        """w (M,) of eq. 8."""

    @property
    def variance_factor(self) -> np.ndarray | None:
        """F of eq. 9 (None: a legacy sparse bundle that stores only F^T F)."""

    def cross(self, Xs: np.ndarray) -> np.ndarray:
        """K(Xs, points) (rows, M)."""

    def reduction_rows(self, Ks: np.ndarray) -> np.ndarray:
        """|F k|^2 of eq. 9 for every row k of Ks (rows,); Ks may be overwritten."""

    def predict(self, Xs: np.ndarray, return_var: bool = True, float32: bool = False):
        """Mean (eq. 8) and latent variance (eq. 9) at the rows of Xs."""

    def mean_grad(self, xs: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Mean, latent variance and d mean / d xs at one point xs (D,)."""

    def mean_var_grad(self, Xs: np.ndarray, block: int = 256, stride: int = 1):
        """``mean_grad`` at every row of Xs: (rows,), (rows,), (rows, D); ``stride`` > 1: eq. 9 at every
        stride-th row (and the last), interpolated between."""

    def arrays(self) -> dict:
        """The arrays a bundle stores (names unchanged across versions)."""
