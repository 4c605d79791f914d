"""Liveness, readiness and Prometheus metrics: open even when an API key is set.

With ``GPNARX_API_KEY`` set, ``/health/ready`` answers a caller without the key its readiness only (status,
bundle and refused counts); the models, refused paths, start-up builds, held scan and audit target are for a
caller that sends the key, as ``/v1/models`` is."""
from __future__ import annotations

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..answers import answer
from ..deps import API_KEY_HEADER, StateDep, key_problem
from ..problems import ProblemError
from ..schemas import Live, Ready

router = APIRouter(tags=["health"])


@router.get("/health/live", response_model=Live, operation_id="health_live", summary="Liveness: the process answers")
async def health_live(request: Request):
    return answer(request, {"status": "alive"})


@router.get("/health/ready", response_model=Ready, operation_id="health_ready",
            summary="Readiness: at least one bundle is loaded (lists refused bundles and start-up builds)",
            description="With GPNARX_API_KEY set, a caller without the key gets `status`, `bundles` and "
                        "`refused_count` only; the other members need the key in X-API-Key.",
            responses={503: {"description": "No bundle loaded (refused bundles listed in `refused`, bundles "
                                            "still being built at start-up in `startup`)"}})
async def health_ready(request: Request, state: StateDep):
    n = state.n_bundles()
    refused = state.refused()
    if key_problem(state.settings.api_key, request.headers.get(API_KEY_HEADER)) is not None:
        # GPNARX_API_KEY set and not sent: readiness and counts only; what /v1/models hides stays hidden
        if n == 0:
            raise ProblemError(503, "no model bundle is loaded", bundles=0, refused_count=len(refused),
                               headers={"Retry-After": str(state.settings.retry_after)})
        return answer(request, {"status": "ready", "bundles": n, "refused_count": len(refused)})
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
            bundles=0, refused=refused, refused_count=len(refused),
            headers={"Retry-After": str(state.settings.retry_after)}, **extra)
    return answer(request, {"status": "ready", "bundles": n, "models": state.models(),
                              "refused": refused, "refused_count": len(refused), **extra})


@router.get("/metrics", operation_id="metrics", summary="Prometheus metrics",
            response_class=Response, responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                                     "description": "Prometheus text exposition format"}})
async def metrics(state: StateDep):
    body, content_type = state.metrics.render()
    return Response(body, media_type=content_type)
