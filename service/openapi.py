"""The service's OpenAPI document: API description (bounds from ``service.settings``), tags, the
problem-detail responses and the optional API key on /v1 routes."""
from __future__ import annotations

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from .deps import RECORD_PROBLEMS
from .observability import REQUEST_ID_HEADER, REQUEST_ID_MAX
from .problems import PROBLEM_MEDIA_TYPE
from .schemas import BatchRequest, Problem
from .settings import DEFAULT_BOUNDS, Settings
from .wire import GZIP_MIN_BYTES, NPZ_MEDIA_TYPE, OCTET_STREAM

API_TITLE = "GP-NARX hysteresis surrogate service"
DEFAULT_REQUEST_TIMEOUT = Settings.model_fields["request_timeout"].default


def api_description() -> str:
    b = DEFAULT_BOUNDS
    return (
        "Free-run prediction with Monte Carlo 99% bands, restoring-force loops and bolt-loosening novelty "
        "scores from GP-NARX surrogates (Teloli et al., MSSP 159 (2021) 107751).\n\n"
        "Errors are RFC 9457 problem details (`application/problem+json`) with `type`, `title`, `status`, "
        "`detail` and the offending `field`.\n\n"
        "Bounds (defaults; environment variable in brackets):\n\n"
        f"- samples per record: {b['max_samples']} [GPNARX_MAX_SAMPLES] -> 413 `u`\n"
        f"- records per batch: {b['max_batch']} [GPNARX_MAX_BATCH] -> 413 `requests`\n"
        f"- Monte Carlo paths: default the model's (`default_mc_paths` of GET /v1/models/{{name}}, its "
        f"config's `[predict] mc_paths`), max {b['mc_paths_max']} "
        f"[GPNARX_MC_PATHS_DEFAULT overrides the model's, GPNARX_MC_PATHS_MAX] -> 422 `mc_paths`\n"
        f"- Monte Carlo work per HTTP request (mc_paths x samples, shared by a batch): {b['max_mc_work']} "
        f"path-steps [GPNARX_MAX_MC_WORK] -> 413 `mc_paths`\n"
        f"- body size: {b['max_body_bytes']} bytes [GPNARX_MAX_BODY_BYTES] -> 413 `body`\n"
        "- work queue: GPNARX_WORKERS running + GPNARX_QUEUE_SIZE waiting jobs -> 503 with Retry-After\n"
        f"- time per compute request (queue wait included): {DEFAULT_REQUEST_TIMEOUT:g} s "
        "[GPNARX_REQUEST_TIMEOUT, 0 = none] -> 504 if the job was running (it is cancelled), 503 with "
        "Retry-After if it was still queued; a client that disconnects cancels its job\n\n"
        f"Compression: an answer of {GZIP_MIN_BYTES} bytes or more is gzip-compressed when the request sends "
        "`Accept-Encoding: gzip` (`Content-Encoding: gzip`, `Vary: Accept-Encoding`). The record routes also take "
        f"NPZ bodies (`{NPZ_MEDIA_TYPE}` or `{OCTET_STREAM}`) and give `{NPZ_MEDIA_TYPE}` answers (see each route's "
        "request body and 200 answer).\n\n"
        "Authentication: off by default. When GPNARX_API_KEY is set, every /v1 route needs the header "
        "`X-API-Key` (401 otherwise); /health/* and /metrics stay open.\n\n"
        "Pages served with the API, from the service's own files (they work offline): /ui (models, "
        "training reports, a record's prediction, PSD, loops and novelty verdict, through this API), "
        "/docs (Swagger UI) and /redoc (ReDoc)."
    )



def _component_schemas(model) -> dict:
    schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
    defs = schema.pop("$defs", {})
    return {model.__name__: schema, **defs}


def build_openapi(app: FastAPI) -> dict:
    """The app's OpenAPI document. The ``ApiKeyAuth`` security scheme (header ``X-API-Key``) is declared, on every
    /v1 operation, only when the app's settings hold an API key (``GPNARX_API_KEY``); the committed
    ``openapi/openapi.json`` (default settings) has none."""
    state = getattr(app.state, "service", None)
    keyed = bool(getattr(getattr(state, "settings", None), "api_key", None))
    doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes,
                      tags=[{"name": "predict", "description": "Predictions, loops, novelty, batch"},
                            {"name": "models", "description": "Model metadata and training reports"},
                            {"name": "records", "description": "Record files parsed into u, y, fs"},
                            {"name": "health", "description": "Liveness, readiness, metrics (always open)"},
                            {"name": "admin", "description": "Registry reload"}])
    comps = doc.setdefault("components", {}).setdefault("schemas", {})
    for model in (Problem, BatchRequest):
        for k, v in _component_schemas(model).items():
            comps.setdefault(k, v)
    for k in ("HTTPValidationError", "ValidationError"):
        comps.pop(k, None)
    problem_ref = {"schema": {"$ref": "#/components/schemas/Problem"}}
    # every answer echoes the request id (service.observability); one header object, referenced by each response
    doc["components"].setdefault("headers", {})["RequestId"] = {
        "description": f"the request's own `{REQUEST_ID_HEADER}` (1 to {REQUEST_ID_MAX} visible ASCII characters), "
                       "else a generated id (32 hex digits); also in the logs, problem details and audit trail",
        "schema": {"type": "string", "minLength": 1, "maxLength": REQUEST_ID_MAX}}
    request_id_ref = {"$ref": "#/components/headers/RequestId"}
    for item in doc.get("paths", {}).values():
        for op in item.values():
            responses = op.setdefault("responses", {})
            responses.setdefault("500", {"description": "Internal error (a problem detail, never a stack trace)"})
            for code, resp in responses.items():
                resp.setdefault("headers", {})[REQUEST_ID_HEADER] = request_id_ref
                if code.isdigit() and int(code) >= 400:
                    resp["content"] = {PROBLEM_MEDIA_TYPE: problem_ref}
                    if code == "422":
                        resp["description"] = RECORD_PROBLEMS[422]
            if not keyed:  # with a key, the key dependency (service.deps) requires the scheme on every /v1 route
                op.pop("security", None)
    if not keyed:  # no key set: no scheme, so Swagger UI shows no lock and no Authorize button
        doc["components"].pop("securitySchemes", None)
    return doc
