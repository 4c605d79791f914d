"""The operations: what the front ends (``gpnarx.service``, ``gpnarx.cli``) do with a loaded bundle, framework-free.

Between the method (``gpnarx.model``) and storage (``gpnarx.storage``) below, and the front ends above
(import contracts in pyproject.toml; docs/architecture.md):

- ``base``: ``Operation`` (plan and compute, the same for every operation), a request (``Request``), the
  bounds it is checked against (``Limits``), its refusals (``OperationError``), the sampling-rate and Monte
  Carlo path rules.
- ``predict``, ``loops``, ``novelty``: one ``Operation`` each (its own checks, free-run options and answer);
  ``run``: the table of them by name (``OPERATIONS``), ``plan`` and ``compute``.
- ``stream_token``: a free run's state as a signed token a client carries between the calls of a stream.
- ``cycle_stream``: the cycles a loops stream has completed so far (what the loops operation carries).
- ``novelty_window``: a novelty stream's rolling window (what the novelty operation carries).
"""
from .base import (
    CONFLICT,
    DEFAULT_MC_PATHS,
    INVALID,
    MC_PATHS_MAX,
    MC_PATHS_MAX_ENV,
    TOO_LARGE,
    Answer,
    Limits,
    Operation,
    OperationError,
    Plan,
    Request,
    check_fs,
    mc_paths_max,
    mc_paths_of,
)
from .loops import physics_of
from .novelty import novelty_of
from .run import OPERATIONS, compute, default_mc_paths, operation, plan

__all__ = ["CONFLICT", "DEFAULT_MC_PATHS", "INVALID", "MC_PATHS_MAX", "MC_PATHS_MAX_ENV", "OPERATIONS", "TOO_LARGE",
           "Answer", "Limits", "Operation", "OperationError", "Plan", "Request", "check_fs", "compute",
           "default_mc_paths", "mc_paths_max", "mc_paths_of", "novelty_of", "operation", "physics_of", "plan"]
