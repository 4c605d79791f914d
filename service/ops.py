"""The service's side of the three operations (``gpnarx.operations`` holds them, shared with the CLI).

``plan`` runs on the event loop (cheap checks against the bundle and the settings' bounds), ``compute``
on a worker thread (cancelled at the free run's next checkpoint once its ``CancelToken`` is set). Both
raise ``ProblemError``: each ``OperationError`` becomes a problem detail naming the field and the limit.
"""
from __future__ import annotations

from gpnarx import operations
from gpnarx.operations import CONFLICT, INVALID, OPERATIONS, TOO_LARGE, Answer, Limits, OperationError, Plan

from .problems import ProblemError
from .settings import Settings
from .worker import CancelToken, JobSize

#: HTTP status of each kind of refusal
STATUS = {INVALID: 422, TOO_LARGE: 413, CONFLICT: 409}


def problem_of(exc: OperationError) -> ProblemError:
    """The problem detail of a refused operation (status by its kind; its limit and extra members kept)."""
    limit = {} if exc.limit is None else {"limit": exc.limit}
    return ProblemError(STATUS[exc.kind], exc.detail, exc.field, **limit, **exc.extra)


def limits_of(settings: Settings) -> Limits:
    """The operations' bounds from the service settings (``GPNARX_MAX_SAMPLES`` ...)."""
    return Limits(max_samples=settings.max_samples, mc_paths_default=settings.mc_paths_default,
                  mc_paths_max=settings.mc_paths_max, max_mc_work=settings.max_mc_work, backend=settings.backend,
                  stream_key=settings.stream_key)


def plan(operation: str, req, bundle, settings: Settings, budget: int | None = None) -> Plan:
    """Check ``req`` (a validated RecordRequest) against ``bundle`` and the settings' bounds."""
    try:
        return operations.plan(operation, req, bundle, limits_of(settings), budget)
    except OperationError as exc:
        raise problem_of(exc) from None


def job_size(plan: Plan) -> JobSize:
    """What ``compute(plan)`` costs, for the worker pool's admission (``worker.CostModel``): its samples and
    Monte Carlo path-steps, under a key naming what sets the cost per sample and per path-step (model and
    version, operation, method, backend)."""
    b = plan.bundle
    samples = plan.work // plan.mc_paths if plan.mc_paths else plan.work
    key = f"{b.name}:{b.version}:{plan.operation}:{plan.method}:{plan.backend}"
    return JobSize.of(key, samples, plan.work if plan.mc_paths else 0)


def compute(plan: Plan, req, token: CancelToken | None = None) -> Answer:
    """Run the operation; ``Answer.body`` is the answer, ``Answer.path_steps`` the Monte Carlo path-steps done.

    ``token``: cooperative cancellation (deadline passed or client gone): ``worker.Cancelled`` is
    raised at the free run's next checkpoint (every 256 samples) once it is set.
    """
    try:
        return operations.compute(plan, req, progress=None if token is None else token.progress,
                                  checkpoint=None if token is None else token.check)
    except OperationError as exc:
        raise problem_of(exc) from None


__all__ = ["OPERATIONS", "Answer", "Plan", "compute", "job_size", "limits_of", "plan", "problem_of"]
