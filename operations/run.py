"""The operations by name, and the two calls every front end makes: ``plan`` (cheap checks, before any work is
queued) and ``compute`` (the free run and the answer). A new operation is a subclass of ``base.Operation`` in a
module of its own, entered in ``OPERATIONS``."""
from __future__ import annotations

from typing import Callable

from .base import Answer, Limits, Operation, OperationError, Plan
from .loops import Loops
from .novelty import Novelty
from .predict import Predict

#: every operation by its name (the HTTP route's and the batch item's ``operation``, the CLI command's)
OPERATIONS: dict[str, Operation] = {op.name: op for op in (Predict(), Loops(), Novelty())}


def operation(name: str) -> Operation:
    """The operation named ``name``; an ``OperationError`` on ``operation`` for any other name."""
    try:
        return OPERATIONS[name]
    except (KeyError, TypeError):
        raise OperationError(f"operation must be one of {tuple(OPERATIONS)}", "operation") from None


def plan(name: str, req, bundle, limits: Limits, budget: int | None = None) -> Plan:
    """Check ``req`` against ``bundle`` and ``limits`` for operation ``name`` (``Operation.plan``). A model with
    several channels (``model.mimo``) is refused on ``model``: answers per channel are not built yet."""
    op = operation(name)
    manifest = getattr(bundle, "manifest", None)
    if isinstance(manifest, dict) and manifest.get("model_class") == "mimo":
        outs = [c.get("name") for c in (manifest.get("channels") or {}).get("outputs", [])]
        raise OperationError(f"model {manifest.get('name')!r} has several channels (outputs {outs}); {name} answers "
                             "per channel are not built yet: use gpnarx.model.mimo.MIMOGPNARX in Python", "model")
    return op.plan(req, bundle, limits, budget)


def compute(plan: Plan, req, *, progress: Callable | None = None,
            checkpoint: Callable[[], None] | None = None) -> Answer:
    """Run the planned operation on ``req`` (``Operation.compute``)."""
    return OPERATIONS[plan.operation].compute(plan, req, progress=progress, checkpoint=checkpoint)


def default_mc_paths(bundle, name: str = "predict") -> int:
    """Monte Carlo paths of operation ``name``'s answer when the request names none: the one rule of the CLI, the
    HTTP service, the /ui page and GET /v1/models/NAME (``Operation.default_mc_paths``)."""
    return operation(name).default_mc_paths(bundle)
