"""The free run (section 2.2 step 3): model predicted output with uncertainty propagation.

``linear`` holds the numpy runs, ``results`` what every run returns, ``jax_backend`` the JAX backend's runs
and ``reference`` the one-step-at-a-time loops the tests and benchmarks compare with.
"""
from .linear import (
    LOCAL_BACKOFF,
    LOCAL_CHECKS,
    LOCAL_EXACT_SHARE,
    LOCAL_MIN_PATHS,
    LOCAL_TOL_MEAN,
    LOCAL_TOL_VAR,
    simulate_linear,
    simulate_mc,
)
from .results import LAG_CLIP, VAR_CAP, FreeRun, FreeRunState, check_state

__all__ = ["FreeRun", "FreeRunState", "LAG_CLIP", "LOCAL_BACKOFF", "LOCAL_CHECKS", "LOCAL_EXACT_SHARE",
           "LOCAL_MIN_PATHS", "LOCAL_TOL_MEAN", "LOCAL_TOL_VAR", "VAR_CAP", "check_state", "simulate_linear",
           "simulate_mc"]
