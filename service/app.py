"""The FastAPI application: ``create_app(registry_dir, settings)``.

Routes (JSON, versioned under /v1; reference in docs/api.md)::

    GET  /v1/models                                   list models
    GET  /v1/models/{name}                            latest version's metadata (+ all versions)
    GET  /v1/models/{name}/versions/{version}         one version's metadata
    POST /v1/models/{name}/predict                    free-run mean, band, std (+ fit, rmse, coverage)
    POST /v1/models/{name}/loops                      restoring-force loops of mean and band edges
    POST /v1/models/{name}/novelty                    novelty score, threshold, verdict
    POST /v1/models/{name}/versions/{version}/{predict|loops|novelty}
    POST /v1/batch                                    many records, each answered or failed alone
    POST /v1/admin/reload                             rescan the registry (also on SIGHUP with serve, and
                                                      by itself every GPNARX_REGISTRY_POLL seconds)
    GET  /v1/models/{name}[/versions/{version}]/report training report; POST /v1/records/parse (routers.ui)
    GET  /ui, /docs, /redoc, /static/...              page and API docs from vendored assets (routers.ui)
    GET  /health/live, /health/ready, /metrics        open even when an API key is set

CPU-heavy work runs on a ``BoundedExecutor`` (503 + Retry-After when full); bodies are capped
(413); a compute request has a deadline (``request_timeout``: 504 when its job was running, 503 +
Retry-After when it was still queued) and a client that disconnects cancels its job; every error
is an RFC 9457 problem detail (``service.problems``).

Layout: ``service.routers`` (one router per group), ``service.deps`` (``Depends`` for the state and
the API key), ``service.state`` (``ServiceState``), ``service.middleware`` (body cap, metrics, last-
resort 500), ``service.responses`` (JSON), ``service.openapi`` (the document), ``service.settings``,
``service.tracing`` (optional OpenTelemetry spans, ``GPNARX_OTEL``).
"""
from __future__ import annotations

import asyncio
import json
import logging
import signal
from contextlib import asynccontextmanager
from functools import partial

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.gzip import GZipMiddleware
from starlette.staticfiles import StaticFiles

from gpnarx.runtime import limit_blas, tune_malloc  # process tuning shared with the CLI

from .deps import API_KEY_HEADER
from .middleware import GuardMiddleware
from .openapi import API_TITLE, api_description, build_openapi
from .problems import ProblemError, validation_problem
from .responses import JSONBytesResponse, parse_json, problem_response, render_json
from .routers import ROUTERS
from .settings import Settings
from .state import ServiceState
from .telemetry import Telemetry
from .tracing import instrument as instrument_tracing
from .ui import STATIC_DIR
from .wire import GZIP_LEVEL, GZIP_MIN_BYTES

log = logging.getLogger("gpnarx.service")


def limit_blas_threads(n: int) -> None:
    """Limit BLAS to ``n`` threads in this process (0: leave it); see ``service.settings``."""
    if not limit_blas(n) and n:  # pragma: no cover - threadpoolctl comes with scikit-learn
        log.warning("threadpoolctl is not installed: BLAS threads are not limited")


def create_app(registry_dir=None, settings: Settings | None = None, startup_status=None) -> FastAPI:
    """The service app over the registry folder ``registry_dir`` (None: an empty registry).

    ``startup_status``: optional callable returning what a launcher is still building into the
    registry (a dict of ``schemas.StartupStatus``'s fields), shown by /health/ready; the launcher
    calls ``app.state.service.reload_from_thread()`` after writing each bundle.
    """
    settings = settings or Settings.from_env()
    limit_blas_threads(settings.blas_threads)
    tune_malloc(settings.mmap_threshold)
    if registry_dir is None and settings.registry:
        registry_dir = settings.registry
    state = ServiceState(registry_dir, settings, startup_status)
    state.telemetry = Telemetry(state)  # audit trail, drift gauges, per-model latency (service.telemetry)
    # /docs and /redoc are served by service.ui from vendored assets (no CDN: they work offline);
    # redirect_slashes=False: Starlette's slash redirect is built from the client's Host header (an open
    # redirect to any host); a path with a trailing slash gets a 404 problem naming the path without it
    app = FastAPI(title=API_TITLE, version="1", description=api_description(), lifespan=lifespan,
                  default_response_class=JSONBytesResponse, docs_url=None, redoc_url=None, redirect_slashes=False)
    app.state.service = state
    add_problem_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    add_middleware(app, state)
    state.metrics.update_bundles()
    app.openapi = partial(cached_openapi, app)
    return app


# ---------------------------------------------------------------------------------------- lifespan
@asynccontextmanager
async def lifespan(app: FastAPI):
    """The app's life: the event loop noted, SIGHUP reloads and the registry poll started; on the way out
    the poll stopped, the workers shut down, the audit lines and the queued spans written."""
    state: ServiceState = app.state.service
    settings = state.settings
    state.loop = asyncio.get_running_loop()
    if settings.sighup_reload:
        reload_on_sighup(state)
    poller = None
    if settings.registry_poll > 0 and state.registry_dir is not None:
        poller = state.loop.create_task(poll_registry(state, settings.registry_poll))
    try:
        yield
    finally:
        if poller is not None:
            poller.cancel()
        state.loop = None
        state.executor.shutdown()
        state.telemetry.close()  # writes the queued audit lines
        provider = getattr(app.state, "tracer_provider", None)
        if provider is not None:  # GPNARX_OTEL: sends the spans still queued
            provider.shutdown()


def reload_on_sighup(state: ServiceState) -> None:
    """Rescan the registry and reopen the audit trail's file on SIGHUP (where the event loop runs in the main
    thread)."""
    if not hasattr(signal, "SIGHUP"):
        return
    loop = asyncio.get_running_loop()

    async def reload():
        try:
            await state.reload()
        except Exception:  # pragma: no cover
            log.exception("reload on SIGHUP failed")

    def on_hup():
        log.info("SIGHUP: reloading the registry and reopening the audit trail's file")
        state.telemetry.audit.reopen()  # logrotate's postrotate `kill -HUP`: later lines go to the new file
        loop.create_task(reload())

    try:
        loop.add_signal_handler(signal.SIGHUP, on_hup)
    except (RuntimeError, ValueError, NotImplementedError):  # not the main thread
        log.info("SIGHUP reload not available in this process")


async def poll_registry(state: ServiceState, every: float) -> None:
    """Rescan the registry every ``every`` seconds (new versions, aliases, changed or removed objects)."""
    while True:
        await asyncio.sleep(every)
        try:
            await state.reload(poll=True)
        except ProblemError as exc:  # store unreachable: the last good registry keeps serving
            log.warning("registry poll: %s", exc.detail)
        except Exception:  # pragma: no cover - a poll must never stop polling
            log.exception("registry poll failed")


# ---------------------------------------------------------------------------------------- problems
async def on_problem(request: Request, exc: ProblemError):
    return problem_response(exc)


async def on_validation_error(request: Request, exc: RequestValidationError):
    return problem_response(validation_problem(list(exc.errors())))


async def on_http_error(request: Request, exc: StarletteHTTPException):
    """Starlette's HTTP errors (no route, wrong method, unreadable body ...) as problem details."""
    status = exc.status_code
    field = None
    if status == 404:
        path = request.url.path[:200]
        hint = f"; without the trailing slash: {path.rstrip('/')}" if path.endswith("/") and path != "/" else ""
        detail = f"no such endpoint: {path} (see /openapi.json{hint})"
    elif status == 405:
        detail = f"method {request.method} is not allowed on {request.url.path[:200]}"
    elif status == 400:
        detail, field = "the request body could not be read as JSON", "body"
    else:
        detail = str(exc.detail)
    return problem_response(ProblemError(status, detail, field, headers=dict(exc.headers or {})))


async def on_unhandled(request: Request, exc: Exception):  # backstop; GuardMiddleware catches first
    log.error("unhandled error on %s %s: %r", request.method, request.url.path, exc)
    return problem_response(ProblemError(500, "internal error; the error was logged"))


def add_problem_handlers(app: FastAPI) -> None:
    """Every error answered as an RFC 9457 problem detail (``service.problems``)."""
    app.add_exception_handler(ProblemError, on_problem)
    app.add_exception_handler(RequestValidationError, on_validation_error)
    app.add_exception_handler(StarletteHTTPException, on_http_error)
    app.add_exception_handler(Exception, on_unhandled)


# ---------------------------------------------------------------------------------------- middleware
def add_middleware(app: FastAPI, state: ServiceState) -> None:
    """gzip when the client accepts it, inside ``GuardMiddleware`` (which still sees every status), and the
    OpenTelemetry spans when ``GPNARX_OTEL`` asks for them (off: nothing of it is imported)."""
    # level 1: on a predict answer's float text it gets nearly all of level 9's size gain for a fraction of
    # the CPU (bench/bench_wire.py); answers under GZIP_MIN_BYTES go as they are
    app.add_middleware(GZipMiddleware, minimum_size=GZIP_MIN_BYTES, compresslevel=GZIP_LEVEL)
    app.add_middleware(GuardMiddleware, state=state, fastapi_app=app)
    if state.settings.otel != "off":
        instrument_tracing(app, state.settings.otel)


def cached_openapi(app: FastAPI) -> dict:
    """The app's OpenAPI document (``service.openapi``), built once."""
    if app.openapi_schema is None:
        app.openapi_schema = build_openapi(app)
    return app.openapi_schema


def openapi_document() -> dict:
    """The OpenAPI document of the service with default settings (what ``openapi/openapi.json`` holds)."""
    return create_app(None, Settings.from_env({}, workers=1, queue_size=0)).openapi()


def openapi_json() -> str:
    """``openapi_document()`` as committed: sorted keys, indent 2, trailing newline."""
    return json.dumps(openapi_document(), sort_keys=True, indent=2, ensure_ascii=False) + "\n"


__all__ = ["API_KEY_HEADER", "JSONBytesResponse", "ServiceState", "create_app", "limit_blas_threads",
           "openapi_document", "openapi_json", "parse_json", "render_json", "tune_malloc"]
