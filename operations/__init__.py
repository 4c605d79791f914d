"""The operations: what the front ends (``gpnarx.service``, ``gpnarx.cli``) do with a loaded bundle, framework-free.

Between the method (``gpnarx.model``) and storage (``gpnarx.storage``) below, and the front ends above
(import contracts in pyproject.toml; docs/architecture.md):

- ``base``: a request (``Request``), the bounds it is checked against (``Limits``), its refusals
  (``OperationError``), the sampling-rate and Monte Carlo path rules, ``plan`` and ``compute``.
- ``stream_token``: a free run's state as a signed token a client carries between the calls of a stream.
- ``cycle_stream``: the cycles a loops stream has completed so far (the loops operation's carry).
- ``novelty_window``: a novelty stream's rolling window (the novelty operation's carry).
"""
from .base import (
    CONFLICT,
    DEFAULT_MC_PATHS,
    INVALID,
    MC_PATHS_MAX,
    MC_PATHS_MAX_ENV,
    OPERATIONS,
    TOO_LARGE,
    Answer,
    Limits,
    OperationError,
    Plan,
    Request,
    check_fs,
    compute,
    default_mc_paths,
    mc_paths_max,
    novelty_of,
    physics_of,
    plan,
    start_of,
)

__all__ = ["CONFLICT", "DEFAULT_MC_PATHS", "INVALID", "MC_PATHS_MAX", "MC_PATHS_MAX_ENV", "OPERATIONS", "TOO_LARGE",
           "Answer", "Limits", "OperationError", "Plan", "Request", "check_fs", "compute", "default_mc_paths",
           "mc_paths_max", "novelty_of", "physics_of", "plan", "start_of"]
