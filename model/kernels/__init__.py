"""Covariance functions as small composable objects (GPflow style), one family per module.

Every kernel holds its hyperparameters in log space (``theta``), so ML-II (eq. 13) optimises an
unconstrained vector. Every kernel meets the core contract ``Kernel`` (covariance, diagonal,
parameters); what ML-II, its workspace, the sparse bound, the linearised free run and the Monte Carlo
local model need beyond it are the small contracts ``GradientKernel``, ``WorkspaceKernel``,
``SparseBoundKernel``, ``LinearisableKernel`` and ``LocalKernel`` (``kernels.base``).

A kernel declares its formula on a family base, which derives every contract from it:
``stationary.StationaryProfile`` (var f(r^2), f a polynomial times an exponential in the scaled distance)
and ``dotproduct.DotProductProfile`` (var (s x.x' + b)^p). Inputs are standardised NARX regressors
(dimensionless). Kernels of the paper:

* ``Matern32``: eq. (10), k1 = sigma_m^2 (1 + sqrt(3) r / l) exp(-sqrt(3) r / l)
* ``CubicPolynomial``: eq. (11), k2 = sigma_p^2 (s x.x' + b)^3
* ``Sum``: eq. (12), k = k1 + k2 (also built by ``k1 + k2``)

plus ``Matern52``, ``RBF`` and ``White``. ``class K(Base, spec="name")`` registers a kernel for
``make_kernel`` and ``kernel_from_dict`` (and as ``kernels.K``).
"""
from __future__ import annotations

import numpy as np

from .base import (
    CONTRACTS,
    DEFAULT_LOG_BOUNDS,
    KERNEL_SPECS,
    KERNEL_TYPES,
    GradientKernel,
    Kernel,
    LinearisableKernel,
    LocalKernel,
    LocalProfile,
    MeanTerms,
    SparseBoundKernel,
    Sum,
    WorkspaceKernel,
    require,
    squared_distances,
)
from .dotproduct import DEFAULT_CONSTANT_CAP, CubicPolynomial, DotProductProfile, check_constant_cap
from .stationary import RBF, Matern32, StationaryProfile
from .white import White


def __getattr__(name: str):
    """A registered kernel by class name (``kernels.Matern52``)."""
    if name in KERNEL_TYPES:
        return KERNEL_TYPES[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def kernel_from_dict(d: dict) -> Kernel:
    """Rebuild a kernel from ``to_dict`` output (bundle manifests). Only registered types are accepted."""
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError("kernel description must be a dict with a 'type'")
    if d["type"] == "Sum":
        return Sum(*[kernel_from_dict(p) for p in d["parts"]])
    cls = KERNEL_TYPES.get(d["type"])
    if cls is None:
        raise ValueError(f"unknown kernel type {d['type']!r}; known: Sum, {', '.join(KERNEL_TYPES)}")
    k = cls.__new__(cls)
    theta = np.asarray(d["theta"], dtype=float)
    if theta.shape != (len(cls.param_names),) or not np.all(np.isfinite(theta)):
        raise ValueError(f"kernel {d['type']} needs {len(cls.param_names)} finite log-parameters")
    k.theta = theta
    k.read_extra(d)
    return k


def make_kernel(spec: str = "matern32+cubic") -> Kernel:
    """Kernel from a short name: 'matern32+cubic' (the paper's eq. 12), 'rbf', 'matern52', 'rbf+cubic', ..."""
    parts = []
    for tok in spec.lower().replace(" ", "").split("+"):
        if tok not in KERNEL_SPECS:
            raise ValueError(f"kernel: unknown part {tok!r} in {spec!r}; use parts of {sorted(KERNEL_SPECS)} "
                             "joined by '+'")
        parts.append(KERNEL_SPECS[tok]())
    return parts[0] if len(parts) == 1 else Sum(*parts)


__all__ = ["CONTRACTS", "DEFAULT_CONSTANT_CAP", "DEFAULT_LOG_BOUNDS", "KERNEL_SPECS", "KERNEL_TYPES", "RBF",
           "CubicPolynomial", "DotProductProfile", "GradientKernel", "Kernel", "LinearisableKernel", "LocalKernel",
           "LocalProfile", "Matern32", "MeanTerms", "SparseBoundKernel", "StationaryProfile", "Sum", "White",
           "WorkspaceKernel", "check_constant_cap", "kernel_from_dict", "make_kernel", "require",
           "squared_distances"]
