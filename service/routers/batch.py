"""Many records in one request: each answered or failed on its own, in order."""
from __future__ import annotations

import logging
import time
import uuid

from fastapi import APIRouter, Request
from pydantic import ValidationError

from .. import ops
from ..deps import RECORD_PROBLEMS, V1, StateDep
from ..problems import ProblemError, validation_problem
from ..responses import JSONBytesResponse, parse_json
from ..schemas import BatchItem, BatchResponse
from ..worker import Cancelled, CancelToken

log = logging.getLogger("gpnarx.service")

router = APIRouter(prefix="/v1", tags=["predict"], dependencies=V1)


@router.post("/batch", response_model=BatchResponse, operation_id="batch",
             summary="Many records: each answered or failed on its own, in order",
             responses={**{k: {"description": RECORD_PROBLEMS[k]} for k in (400, 401, 413, 422, 503, 504)},
                        415: {"description": "Body is not application/json"}},
             openapi_extra={"requestBody": {"required": True, "content": {"application/json": {
                 "schema": {"$ref": "#/components/schemas/BatchRequest"}}}}})
async def batch(request: Request, state: StateDep):
    settings = state.settings
    ctype = request.headers.get("content-type", "")
    if ctype and "json" not in ctype.split(";")[0].lower():
        raise ProblemError(415, f"the body must be application/json, got {ctype[:100]!r}", "body")
    raw = await request.body()
    try:
        data = parse_json(raw)
    except ValueError as exc:
        raise ProblemError(400, str(exc), "body") from None
    if not isinstance(data, dict):
        raise ProblemError(422, "the body must be a JSON object {\"requests\": [...]}", "body")
    extra = sorted(set(data) - {"requests"})
    if extra:
        raise ProblemError(422, f"unknown field {extra[0]!r}: the body holds only `requests`", str(extra[0]))
    items = data.get("requests")
    if not isinstance(items, list):
        raise ProblemError(422, "requests must be a list of records", "requests")
    if len(items) == 0:
        raise ProblemError(422, "requests must hold at least one record", "requests")
    if len(items) > settings.max_batch:
        raise ProblemError(413, f"requests holds {len(items)} records; the limit is {settings.max_batch} per "
                                f"batch", "requests", limit=settings.max_batch)
    results: list = [None] * len(items)
    todo = []
    budget = settings.max_mc_work
    for i, item in enumerate(items):
        prefix = f"requests.{i}"
        try:
            req = BatchItem.model_validate(item)
        except ValidationError as exc:
            results[i] = validation_problem(list(exc.errors())).to_dict(prefix)
            continue
        try:
            bundle = await state.alookup(req.model, req.version)
            plan = ops.plan(req.operation, req, bundle, settings, budget=budget)
        except ProblemError as exc:
            if exc.field in ("name", "version"):
                exc.field = "model" if exc.field == "name" else "version"
            results[i] = exc.to_dict(prefix)
            continue
        budget -= plan.work if plan.method == "mc" else 0
        todo.append((i, plan, req))

    def run_all(token):
        done, steps = [], 0
        for i, plan, req in todo:
            token.check()  # deadline passed or client gone: stop between records
            try:
                t0 = time.perf_counter()
                out, s = ops.compute(plan, req, token)
                steps += s
                done.append((i, out))
                state.metrics.answered(plan.operation, out)
                state.telemetry.answered(request, plan.operation, out, req, time.perf_counter() - t0, slot=i)
            except Cancelled:
                raise
            except ProblemError as exc:
                done.append((i, exc.to_dict(f"requests.{i}")))
            except Exception:  # one bad record never loses the others
                incident = uuid.uuid4().hex[:12]
                log.exception("batch record %d failed (incident %s)", i, incident)
                done.append((i, ProblemError(500, f"internal error on this record (incident {incident})",
                                             incident=incident).to_dict(f"requests.{i}")))
        return done, steps

    if todo:
        token = CancelToken()
        done, steps = await state.run(run_all, token, request=request, token=token,
                                      work=sum(plan.work for _, plan, _ in todo))
        state.metrics.path_steps.inc(steps)
        for i, out in done:
            results[i] = out
    return JSONBytesResponse({"results": results})
