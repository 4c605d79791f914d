"""Predictions, restoring-force loops and novelty scores of one record (latest or one version)."""
from __future__ import annotations

import time

from fastapi import APIRouter, Request

from .. import ops
from ..deps import RECORD_PROBLEMS, V1, NameP, StateDep, VersionP
from ..responses import JSONBytesResponse
from ..schemas import LoopsResponse, NoveltyRequest, NoveltyResponse, PredictResponse, RecordRequest
from ..state import ServiceState
from ..worker import CancelToken

router = APIRouter(prefix="/v1", tags=["predict"], dependencies=V1)

op_problems = {k: {"description": v} for k, v in RECORD_PROBLEMS.items()}
loops_problems = {**op_problems, 409: {"description": "The bundle has no physical constants (mass)"}}
novelty_problems = {**op_problems, 409: {"description": "The bundle has no novelty calibration"}}


def timed_compute(plan, body, submitted, token):
    started = time.perf_counter()
    out, steps = ops.compute(plan, body, token)
    return out, steps, started - submitted, time.perf_counter() - started


async def single(state: ServiceState, request: Request, operation: str, body: RecordRequest, name: str,
                 version: str | None):
    """One record's answer, computed on the worker pool (``Server-Timing``: queue and compute time)."""
    bundle = await state.alookup(name, version)
    plan = ops.plan(operation, body, bundle, state.settings)
    token = CancelToken()
    out, steps, waited, computed = await state.run(timed_compute, plan, body, time.perf_counter(), token,
                                                   request=request, token=token)
    state.metrics.path_steps.inc(steps)
    state.metrics.answered(operation, out)
    return JSONBytesResponse(out, headers={
        "Server-Timing": f"queue;dur={waited * 1e3:.2f}, compute;dur={computed * 1e3:.2f}"})


@router.post("/models/{name}/predict", response_model=PredictResponse, operation_id="predict",
             summary="Free-run prediction with a Monte Carlo band (latest version)", responses=op_problems)
async def predict(request: Request, state: StateDep, name: NameP, body: RecordRequest):
    return await single(state, request, "predict", body, name, None)


@router.post("/models/{name}/versions/{version}/predict", response_model=PredictResponse,
             operation_id="predict_version", summary="Free-run prediction with one version", responses=op_problems)
async def predict_version(request: Request, state: StateDep, name: NameP, version: VersionP, body: RecordRequest):
    return await single(state, request, "predict", body, name, version)


@router.post("/models/{name}/loops", response_model=LoopsResponse, operation_id="loops",
             summary="Restoring-force loops of the predicted response and its band (latest version)",
             responses=loops_problems)
async def loops(request: Request, state: StateDep, name: NameP, body: RecordRequest):
    return await single(state, request, "loops", body, name, None)


@router.post("/models/{name}/versions/{version}/loops", response_model=LoopsResponse, operation_id="loops_version",
             summary="Restoring-force loops with one version", responses=loops_problems)
async def loops_version(request: Request, state: StateDep, name: NameP, version: VersionP, body: RecordRequest):
    return await single(state, request, "loops", body, name, version)


@router.post("/models/{name}/novelty", response_model=NoveltyResponse, operation_id="novelty",
             summary="Novelty score, threshold and verdict of a measured record (latest version)",
             responses=novelty_problems)
async def novelty(request: Request, state: StateDep, name: NameP, body: NoveltyRequest):
    return await single(state, request, "novelty", body, name, None)


@router.post("/models/{name}/versions/{version}/novelty", response_model=NoveltyResponse,
             operation_id="novelty_version", summary="Novelty score with one version", responses=novelty_problems)
async def novelty_version(request: Request, state: StateDep, name: NameP, version: VersionP, body: NoveltyRequest):
    return await single(state, request, "novelty", body, name, version)
