"""Predictions, restoring-force loops and novelty scores of one record (latest or one version)."""
from __future__ import annotations

import time

from fastapi import APIRouter, Request
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response

from .. import ops
from ..answers import checked
from ..bodies import declared_length, is_large, off_loop, parse_or_none, validated
from ..deps import RECORD_PROBLEMS, V1, NameP, StateDep, VersionP
from ..problems import ProblemError
from ..responses import JSONBytesResponse
from ..schemas import LoopsResponse, NoveltyRequest, NoveltyResponse, PredictResponse, RecordRequest
from ..state import ServiceState, too_slow_advice
from ..wire import (
    NPZ_BODY_MEDIA_TYPES,
    NPZ_MEDIA_TYPE,
    OCTET_STREAM,
    check_units,
    npz_request_fields,
    render_npz,
    wants_npz,
)
from ..worker import CancelToken

#: what a record route's body may be sent as (a ``+json`` suffix type counts as JSON, as FastAPI reads it)
RECORD_MEDIA_TYPES = ("application/json", *NPZ_BODY_MEDIA_TYPES)
#: the request scope's key of an NPZ body's unit labels (``wire.read_npz_body``), checked once the model is known
NPZ_UNITS = "gpnarx.npz_units"


def check_content_type(ctype: str) -> None:
    """A 422 problem naming the ``content-type`` header when a record body is sent as anything but JSON or NPZ
    (FastAPI would otherwise not read it and answer that the body is not an object)."""
    if ctype in RECORD_MEDIA_TYPES or (ctype.startswith("application/") and ctype.endswith("+json")):
        return
    got = f"'{ctype}'" if ctype else "no content-type header"
    raise ProblemError(422, f"the body was sent with {got}; send the header content-type: "
                            f"{' or '.join(RECORD_MEDIA_TYPES)} (a JSON record, or an NPZ archive with the "
                            f"other fields as query parameters)", "content-type", accepted=list(RECORD_MEDIA_TYPES))


class RecordRoute(APIRoute):
    """A record route that also takes an NPZ body (``service.wire``): the archive's arrays and the
    query's fields become the JSON body the route's schema validates (same limits, same problems).

    A large body (JSON of at least ``bodies.OFF_LOOP_BYTES``, or NPZ) is read and validated by the route's body
    model on a worker thread (``service.bodies``); FastAPI is handed the validated
    model, which it takes as it is. A validation error is raised as FastAPI raises it (the same problem);
    a JSON body that does not parse goes FastAPI's own way (the same 400). A body sent with another
    content-type, or none, is a 422 naming the header and the accepted types (``check_content_type``).
    """

    def get_route_handler(self):
        handler = super().get_route_handler()
        model = self.body_field.field_info.annotation

        async def route_handler(request: Request) -> Response:
            ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
            check_content_type(ctype)
            size = declared_length(request)
            units: dict = {}
            if ctype in NPZ_BODY_MEDIA_TYPES:
                settings = request.app.state.service.settings
                fields = await run_in_threadpool(npz_request_fields, await request.body(), request.query_params,
                                                 settings.max_body_bytes, settings.max_samples, units)
            elif ctype == "application/json" and is_large(size):
                fields = await off_loop(size, parse_or_none, await request.body())
                if fields is None:  # not JSON: FastAPI answers it (400, its message)
                    return await handler(request)
            else:
                return await handler(request)
            body = await run_in_threadpool(validated, model, fields)
            headers = [(k, v) for k, v in request.scope["headers"] if k.lower() != b"content-type"]
            scope = {**request.scope, "headers": [*headers, (b"content-type", b"application/json")],
                     "query_string": b"", NPZ_UNITS: units}
            as_json = Request(scope, request.receive)
            as_json._body = b"parsed"  # already read; FastAPI only needs it non-empty
            as_json._json = body
            return await handler(as_json)

        return route_handler


router = APIRouter(prefix="/v1", tags=["predict"], dependencies=V1, route_class=RecordRoute)

#: the NPZ body and answer of the record routes, merged into their OpenAPI operations. The body is documented
#: under the generic binary type, which client generators understand (openapi-python-client makes it a ``File``
#: body and warns on a vendor type); ``application/x-npz`` is the same body
NPZ_OPENAPI = {
    "requestBody": {"content": {OCTET_STREAM: {"schema": {
        "type": "string", "format": "binary",
        "description": f"An .npz archive (also accepted as `{NPZ_MEDIA_TYPE}`) with the 1-D arrays `u`, `y`, `y0` "
                       "(integer or floating point) and the scalar `fs` [Hz], and optionally the unit labels "
                       "`units_u`, `units_y` (checked against the model's) and `name` (ignored) of a record file "
                       "the package writes; the other fields are query parameters. Read without pickle; its "
                       "decompressed size is bounded by GPNARX_MAX_BODY_BYTES (413 naming the array); a body "
                       "that is not a zip archive is a 400, a corrupt member or a wrong dtype a 422 naming the "
                       "array."}}}},
    "parameters": [
        {"name": n, "in": "query", "required": False, "description": f"With an NPZ body only: the body field `{n}`.",
         "schema": sch}
        for n, sch in (("fs", {"type": "number"}), ("mc_paths", {"type": "integer"}), ("seed", {"type": "integer"}),
                       ("confidence", {"type": "number"}), ("method", {"type": "string", "enum": ["mc", "linear"]}),
                       ("backend", {"type": "string", "enum": ["numpy", "jax"]}),
                       ("start", {"type": "string", "enum": ["rest", "measured"]}),
                       ("return_state", {"type": "boolean"}), ("state", {"type": "string"}))],
}
NPZ_ANSWER = {NPZ_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary", "description": (
    "With `Accept: application/x-npz`: each list of numbers of the JSON answer as a float64 array (`mean`, "
    "`lower`, `upper`, `std`, ...; null as NaN), each number a 0-d array, each string a 0-d unicode array, "
    "the other fields as a JSON object in the 0-d unicode array `json`. Uncompressed; gzip applies when "
    "accepted.")}}}

op_problems = {k: {"description": v} for k, v in RECORD_PROBLEMS.items()}
op_problems[200] = {"content": NPZ_ANSWER}
loops_problems = {**op_problems, 409: {"description": "The bundle has no physical constants (mass)"}}
novelty_problems = {**op_problems, 409: {"description": "The bundle has no novelty calibration"}}


def timed_compute(plan, body, submitted, token):
    started = time.perf_counter()
    answer = ops.compute(plan, body, token)
    return answer.body, answer.path_steps, started - submitted, time.perf_counter() - started


async def single(state: ServiceState, request: Request, operation: str, body: RecordRequest, name: str,
                 version: str | None):
    """One record's answer, computed on the worker pool (``Server-Timing``: queue and compute time)."""
    bundle = await state.alookup(name, version)
    units = request.scope.get(NPZ_UNITS)
    if units:  # an NPZ body's unit labels (a record file's): the model's units, or a 422 naming the label
        check_units(units, bundle)
    # a long stream token is decoded while planning: on a worker thread, as a large body is parsed
    plan = await off_loop(len(body.state or ""), ops.plan, operation, body, bundle, state.settings)
    token = CancelToken()
    out, steps, waited, computed = await state.run(timed_compute, plan, body, time.perf_counter(), token,
                                                   request=request, token=token, work=ops.job_size(plan),
                                                   too_slow=too_slow_advice(plan.method == "mc"))
    state.metrics.path_steps.inc(steps)
    state.metrics.answered(operation, out)
    state.telemetry.answered(request, operation, out, body, waited + computed)  # audit line, drift, latency
    checked(request, out)  # the route's response model, whichever format the answer goes in
    headers = {"Server-Timing": f"queue;dur={waited * 1e3:.2f}, compute;dur={computed * 1e3:.2f}",
               "Vary": "Accept"}
    if wants_npz(request.headers.get("accept")):
        return Response(render_npz(out), media_type=NPZ_MEDIA_TYPE, headers=headers)
    return JSONBytesResponse(out, headers=headers)


def record_routes(operation: str, response_model, body_model, *, summary: str, version_summary: str,
                  responses: dict) -> None:
    """Operation ``operation``'s two routes on ``router``: ``/models/{name}/OPERATION`` (the latest version,
    operation id ``OPERATION``) and ``/models/{name}/versions/{version}/OPERATION`` (operation id
    ``OPERATION_version``), each answering a ``body_model`` body with ``response_model`` through ``single``."""

    async def latest(request: Request, state: StateDep, name: NameP, body):
        return await single(state, request, operation, body, name, None)

    async def version(request: Request, state: StateDep, name: NameP, version: VersionP, body):
        return await single(state, request, operation, body, name, version)

    for handler, path, op_id, text in ((latest, f"/models/{{name}}/{operation}", operation, summary),
                                       (version, f"/models/{{name}}/versions/{{version}}/{operation}",
                                        f"{operation}_version", version_summary)):
        handler.__annotations__["body"] = body_model  # the body FastAPI validates (the annotation it reads)
        handler.__name__ = handler.__qualname__ = op_id
        router.add_api_route(path, handler, methods=["POST"], response_model=response_model, operation_id=op_id,
                             summary=text, responses=responses, openapi_extra=NPZ_OPENAPI)


record_routes("predict", PredictResponse, RecordRequest, responses=op_problems,
              summary="Free-run prediction with a Monte Carlo band (latest version)",
              version_summary="Free-run prediction with one version")
record_routes("loops", LoopsResponse, RecordRequest, responses=loops_problems,
              summary="Restoring-force loops of the predicted response and its band (latest version)",
              version_summary="Restoring-force loops with one version")
record_routes("novelty", NoveltyResponse, NoveltyRequest, responses=novelty_problems,
              summary="Novelty score, threshold and verdict of a measured record (latest version)",
              version_summary="Novelty score with one version")
