"""Many records in one request: each answered or failed on its own, in order.

A large body (``bodies.OFF_LOOP_BYTES`` or more) is parsed and its records validated on a worker
thread (``bodies.off_loop``, as the record routes do), so a flood of big batches never stalls the
event loop; the records are then planned on the loop (cheap checks) and computed on the worker pool.
"""
from __future__ import annotations

import logging
import time
import uuid

from fastapi import APIRouter, Request
from pydantic import ValidationError

from .. import ops
from ..answers import answer
from ..bodies import off_loop
from ..deps import RECORD_PROBLEMS, V1, StateDep
from ..problems import ProblemError, validation_problem
from ..responses import parse_json
from ..schemas import BatchItem, BatchResponse
from ..state import too_slow_advice
from ..worker import Cancelled, CancelToken, JobSize

log = logging.getLogger("gpnarx.service")

router = APIRouter(prefix="/v1", tags=["predict"], dependencies=V1)


@router.post("/batch", response_model=BatchResponse, operation_id="batch",
             summary="Many records: each answered or failed on its own, in order",
             responses={**{k: {"description": RECORD_PROBLEMS[k]} for k in (400, 401, 413, 422, 503, 504)},
                        415: {"description": "Body is not application/json"}},
             openapi_extra={"requestBody": {"required": True, "content": {"application/json": {
                 "schema": {"$ref": "#/components/schemas/BatchRequest"}}}}})
async def batch(request: Request, state: StateDep):
    raw = await request.body()
    items = await off_loop(len(raw), read_items, raw, request.headers.get("content-type", ""),
                           state.settings.max_batch)
    results, todo = await plan_items(state, items)
    if todo:
        token = CancelToken()
        done, steps = await state.run(run_items, state, request, todo, token, request=request, token=token,
                                      work=sum((ops.job_size(plan) for _, plan, _ in todo), JobSize(())),
                                      too_slow=too_slow_advice(any(p.method == "mc" for _, p, _ in todo), batch=True))
        state.metrics.path_steps.inc(steps)
        for i, out in done:
            results[i] = out
    return answer(request, {"results": results})


def read_items(raw: bytes, ctype: str, max_batch: int) -> list:
    """The records of a batch body, each a validated ``BatchItem`` or the problem (a dict located at
    ``requests.I``) that refuses it; a ProblemError for the body as a whole."""
    if ctype and "json" not in ctype.split(";")[0].lower():
        raise ProblemError(415, f"the body must be application/json, got {ctype[:100]!r}", "body")
    if not raw.strip():
        raise ProblemError(422, "the body is empty: send a JSON object {\"requests\": [...]}", "body")
    try:
        data = parse_json(raw, non_finite=True)  # a non-finite number is its record's 422, not the batch's
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
    if len(items) > max_batch:
        raise ProblemError(413, f"requests holds {len(items)} records; the limit is {max_batch} per batch",
                           "requests", limit=max_batch)
    out: list = []
    for i, item in enumerate(items):
        try:
            out.append(BatchItem.model_validate(item))
        except ValidationError as exc:
            out.append(validation_problem(list(exc.errors())).to_dict(f"requests.{i}"))
    return out


async def plan_items(state, items: list) -> tuple[list, list]:
    """(results with each refused record's problem in its slot, [(slot, plan, request)] to compute) of
    ``read_items``' records; the records share one Monte Carlo work budget."""
    results: list = [None] * len(items)
    todo = []
    budget = state.settings.max_mc_work
    for i, req in enumerate(items):
        prefix = f"requests.{i}"
        if not isinstance(req, BatchItem):  # refused by validation: its problem
            results[i] = req
            continue
        try:
            bundle = await state.alookup(req.model, req.version)
            # a long stream token is decoded while planning: on a worker thread, as a large body is parsed
            plan = await off_loop(len(req.state or ""), ops.plan, req.operation, req, bundle, state.settings,
                                  budget)
        except ProblemError as exc:
            if exc.field in ("name", "version"):
                exc.field = "model" if exc.field == "name" else "version"
            results[i] = exc.to_dict(prefix)
            continue
        except Exception:  # one bad record never loses the others
            results[i] = _internal_error(i, "could not be planned")
            continue
        budget -= plan.work if plan.method == "mc" else 0
        todo.append((i, plan, req))
    return results, todo


def run_items(state, request, todo: list, token) -> tuple[list, int]:
    """Compute the planned records in order on a worker: ([(slot, answer or problem)], path-steps)."""
    done, steps = [], 0
    total, before = sum(max(plan.work, 1) for _, plan, _ in todo), 0
    for i, plan, req in todo:
        token.check()  # deadline passed or client gone: stop between records
        token.span = (before / total, max(plan.work, 1) / total)  # the batch's progress, not the record's
        before += max(plan.work, 1)
        try:
            t0 = time.perf_counter()
            out = ops.compute(plan, req, token)
            steps += out.path_steps
            done.append((i, out.body))
            state.metrics.answered(plan.operation, out.body)
            state.telemetry.answered(request, plan.operation, out.body, req, time.perf_counter() - t0, slot=i)
        except Cancelled:
            raise
        except ProblemError as exc:
            done.append((i, exc.to_dict(f"requests.{i}")))
        except Exception:  # one bad record never loses the others
            done.append((i, _internal_error(i, "failed")))
    return done, steps


def _internal_error(i: int, what: str) -> dict:
    """The 500 problem of batch record ``i`` that raised unexpectedly, its traceback logged under an incident id."""
    incident = uuid.uuid4().hex[:12]
    log.exception("batch record %d %s (incident %s)", i, what, incident)
    return ProblemError(500, f"internal error on this record (incident {incident})",
                        incident=incident).to_dict(f"requests.{i}")
