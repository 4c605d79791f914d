"""The free run's runners by (method, backend): each a function ``runner(predictor, u, spec) -> FreeRun``.

``run`` hands a ``Predictor`` and a ``RunSpec`` to the runner of ``(spec.method, spec.backend)``. A new method or
backend is a runner in a module of its own and one entry in ``RUNNERS``; an optional backend's module is imported
only when its runner is called, so a numpy process never loads it.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .linear import run_linear
from .mc import run_mc
from .results import FreeRun
from .spec import Predictor, RunSpec

Runner = Callable[[Predictor, np.ndarray, RunSpec], FreeRun]


def _mc_jax(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    from .jax_backend import run_mc_jax

    return run_mc_jax(predictor, u, spec)


def _linear_jax(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    from .jax_backend import run_linear_jax

    return run_linear_jax(predictor, u, spec)


RUNNERS: dict[tuple[str, str], Runner] = {
    ("mc", "numpy"): run_mc,
    ("linear", "numpy"): run_linear,
    ("mc", "jax"): _mc_jax,
    ("linear", "jax"): _linear_jax,
}
METHODS = tuple(dict.fromkeys(method for method, _ in RUNNERS))  # ('mc', 'linear')


def check_method(method) -> str:
    """``method`` if a runner has it, else a ValueError naming the methods."""
    if method not in METHODS:
        raise ValueError(f"method must be {' or '.join(repr(m) for m in METHODS)}, got {method!r}")
    return method


def run(predictor: Predictor, u: np.ndarray, spec: RunSpec) -> FreeRun:
    """The free run of input ``u`` (input units) that ``spec`` asks for, on ``predictor``'s model."""
    runner = RUNNERS.get((check_method(spec.method), spec.backend))
    if runner is None:
        backends = [b for m, b in RUNNERS if m == spec.method]
        raise ValueError(f"method {spec.method!r} runs on backend {' or '.join(map(repr, backends))}, "
                         f"got {spec.backend!r}")
    return runner(predictor, u, spec)
