"""Liveness, readiness and Prometheus metrics: open even when an API key is set."""
from __future__ import annotations

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..answers import answer
from ..deps import StateDep
from ..problems import ProblemError
from ..schemas import Live, Ready

router = APIRouter(tags=["health"])


@router.get("/health/live", response_model=Live, operation_id="health_live", summary="Liveness: the process answers")
async def health_live(request: Request):
    return answer(request, {"status": "alive"})


@router.get("/health/ready", response_model=Ready, operation_id="health_ready",
            summary="Readiness: at least one bundle is loaded (lists refused bundles and start-up builds)",
            responses={503: {"description": "No bundle loaded (refused bundles listed in `refused`, bundles "
                                            "still being built at start-up in `startup`)"}})
async def health_ready(request: Request, state: StateDep):
    n = state.n_bundles()
    startup = state.startup()
    extra = {} if startup is None else {"startup": startup}
    extra["audit"] = state.telemetry.ready()  # a failing audit target shows here; readiness does not fail
    if state.held:
        extra["registry_held"] = state.held
    if n == 0:
        building = [*(startup or {}).get("building", []), *(startup or {}).get("pending", [])]
        raise ProblemError(503, "no model bundle is loaded" + (
            f"; {len(state.registry.refused)} refused (see `refused`)" if state.registry.refused else "") + (
            f"; building {', '.join(building)} (see `startup`)" if building else "") + (
            f"; the registry could not be read: {state.registry_error}" if state.registry_error else ""),
            bundles=0, refused=state.refused(), headers={"Retry-After": str(state.settings.retry_after)}, **extra)
    return answer(request, {"status": "ready", "bundles": n, "models": state.models(),
                              "refused": state.refused(), **extra})


@router.get("/metrics", operation_id="metrics", summary="Prometheus metrics",
            response_class=Response, responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                                     "description": "Prometheus text exposition format"}})
async def metrics(state: StateDep):
    body, content_type = state.metrics.render()
    return Response(body, media_type=content_type)
