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
    GET  /v1/models/{name}[/versions/{version}]/report training report; POST /v1/records/parse (service.ui)
    GET  /ui, /docs, /redoc, /static/...              page and API docs from vendored assets (service.ui)
    GET  /health/live, /health/ready, /metrics        open even when an API key is set

CPU-heavy work runs on a ``BoundedExecutor`` (503 + Retry-After when full); bodies are capped
(413); a compute request has a deadline (``request_timeout``: 504 when its job was running, 503 +
Retry-After when it was still queued) and a client that disconnects cancels its job; every error
is an RFC 9457 problem detail (``service.problems``).
"""
from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import signal
import time
import uuid
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse, Response
from starlette.routing import Match

from gpnarx.model.bundle import BundleError, Registry, check_name, check_version_ref
from gpnarx.model.runtime import limit_blas, tune_malloc  # process tuning shared with the CLI
from gpnarx.model.storage import StorageError

from . import ops, ui
from .metrics import ServiceMetrics
from .problems import PROBLEM_MEDIA_TYPE, ProblemError, validation_problem
from .schemas import (
    NAME_PATTERN,
    VERSION_PATTERN,
    BatchItem,
    BatchRequest,
    BatchResponse,
    Live,
    LoopsResponse,
    ModelDetail,
    ModelList,
    NoveltyRequest,
    NoveltyResponse,
    PredictResponse,
    Problem,
    Ready,
    RecordRequest,
    ReloadResponse,
)
from .settings import DEFAULT_BOUNDS, Settings
from .worker import (
    Abandoned,
    BoundedExecutor,
    Cancelled,
    CancelToken,
    Overloaded,
    QueueTimeout,
    TimedOut,
)

log = logging.getLogger("gpnarx.service")
DEFAULT_REQUEST_TIMEOUT = Settings.__dataclass_fields__["request_timeout"].default

API_TITLE = "GP-NARX hysteresis surrogate service"
API_KEY_HEADER = "X-API-Key"

try:  # fast JSON for long float arrays
    import orjson as _orjson
except ImportError:  # pragma: no cover - exercised only without orjson
    _orjson = None


# ------------------------------------------------------------------------------------------ JSON
def _sanitize(obj):
    if isinstance(obj, dict):
        return {str(k): _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _sanitize(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def render_json(obj) -> bytes:
    """JSON bytes; numpy arrays serialised natively (orjson) and non-finite floats as null."""
    if _orjson is not None:
        return _orjson.dumps(obj, option=_orjson.OPT_SERIALIZE_NUMPY | _orjson.OPT_NON_STR_KEYS)
    return json.dumps(_sanitize(obj), separators=(",", ":"), allow_nan=False).encode()


def parse_json(raw: bytes):
    """Parse a request body; ``ValueError`` with a clear message when it is not JSON."""
    if _orjson is not None:
        try:
            return _orjson.loads(raw)
        except _orjson.JSONDecodeError as exc:
            raise ValueError(f"request body is not valid JSON: {exc}") from None
    try:
        return json.loads(raw, parse_constant=_refuse_constant)
    except RecursionError:
        raise ValueError("request body is not valid JSON: nested too deeply") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"request body is not valid JSON: {exc}") from None


def _refuse_constant(name):
    raise json.JSONDecodeError(f"{name} is not a JSON number", name, 0)


class JSONBytesResponse(JSONResponse):
    """JSON answer rendered by ``render_json`` (numpy arrays without a Python-float detour)."""

    media_type = "application/json"

    def render(self, content: Any) -> bytes:
        return render_json(content)


class ProblemResponse(JSONBytesResponse):
    media_type = PROBLEM_MEDIA_TYPE


def problem_response(p: ProblemError) -> ProblemResponse:
    return ProblemResponse(p.to_dict(), status_code=p.status, headers=p.headers)


# ------------------------------------------------------------------------------------------ state
class ServiceState:
    """Registry (swapped atomically on reload), executor, metrics and settings of one app.

    The registry is lazy: every version is verified when first seen, its model built on first use
    (at most ``settings.max_loaded`` kept). ``reload`` (admin route, SIGHUP) and the poll
    (``settings.registry_poll``) swap in a rescan; a registry that cannot be read keeps the last
    good one serving (``registry_error`` says why).
    """

    def __init__(self, registry_dir, settings: Settings, startup_status=None):
        self.settings = settings
        # start-up hook: a callable returning a dict (schemas.StartupStatus) of the bundles a launcher is
        # still building into the registry (``gpnarx serve`` without --registry); shown by /health/ready
        self.startup_status = startup_status
        self.loop: asyncio.AbstractEventLoop | None = None  # the server's loop while the app runs
        self.registry_dir = registry_dir if registry_dir else None  # a folder or an fsspec URL
        self.registry = Registry(self.registry_dir or Path("/nonexistent-gpnarx-registry"), lazy=True,
                                 max_loaded=settings.max_loaded)
        self.registry_error: str | None = None
        if self.registry_dir is not None:
            try:
                self.registry.scan()
            except StorageError as exc:  # unreachable store: not ready; the poll and reload try again
                self.registry_error = str(exc)
                log.error("the registry could not be read: %s", exc)
        self.executor = BoundedExecutor(settings.workers, settings.queue_size)
        self.metrics = ServiceMetrics(self)
        self.reload_lock = asyncio.Lock()
        self.reloads = 0
        self.polls = 0
        self._reported = self._listed(self.registry)  # what the last reload answered against

    def refused(self, registry: Registry | None = None) -> list[dict]:
        reg = registry or self.registry
        root = str(reg.root).rstrip("/") + "/"
        out = []
        for r in reg.refused:
            path = r["path"][len(root):] if r["path"].startswith(root) else Path(r["path"]).name
            out.append({"path": path, "reason": r["reason"].replace(root, "")})
        return out

    def models(self, registry: Registry | None = None) -> dict:
        reg = registry or self.registry
        return {name: reg.versions(name) for name in reg.names()}

    def n_bundles(self, registry: Registry | None = None) -> int:
        reg = registry or self.registry
        return sum(len(v) for v in reg.bundles.values())

    @staticmethod
    def _listed(reg: Registry) -> set:
        return {f"{n}:{v}" for n, vs in reg.bundles.items() for v in vs}

    async def reload(self, poll: bool = False) -> dict:
        """Rescan the registry and swap it in. ``added``/``removed`` compare with the previous reload
        (or the start), so versions a poll picked up meanwhile are still reported; a poll does not
        move that reference."""
        if self.registry_dir is None:
            raise ProblemError(409, "no registry folder is configured; nothing to reload")
        async with self.reload_lock:
            old = self.registry
            try:
                new = await asyncio.to_thread(old.rescan)
            except StorageError as exc:
                self.registry_error = str(exc)
                raise ProblemError(503, f"the registry could not be read ({exc}); the versions listed before "
                                        f"keep serving", headers={"Retry-After": str(self.settings.retry_after)}
                                   ) from None
            self.registry = new  # atomic swap: in-flight requests keep the bundle they hold
            self.registry_error = None
            if poll:
                self.polls += 1
            else:
                self.reloads += 1
            before, after = (self._listed(old), self._listed(new)) if poll else (self._reported, self._listed(new))
            if not poll:
                self._reported = after
        self.metrics.update_bundles()
        if not poll or before != after or len(old.refused) != len(new.refused):
            log.info("registry %s: %d bundles, %d refused; added %s, removed %s", "polled" if poll else "reloaded",
                     self.n_bundles(new), len(new.refused), sorted(after - before) or "none",
                     sorted(before - after) or "none")
        return {"bundles": self.n_bundles(new), "models": self.models(new), "refused": self.refused(new),
                "added": sorted(after - before), "removed": sorted(before - after)}

    def reload_from_thread(self, timeout: float | None = 300.0) -> dict:
        """``reload()`` called from another thread (e.g. a launcher that has just written a bundle).

        Runs on the server's event loop while the app runs (so it takes turns with admin reloads), else
        in this thread; returns reload()'s answer.
        """
        loop = self.loop
        if loop is not None and loop.is_running():
            return asyncio.run_coroutine_threadsafe(self.reload(), loop).result(timeout)
        return asyncio.run(self.reload())

    def startup(self) -> dict | None:
        """The start-up hook's status (None without a hook, or if the hook fails: logged)."""
        if self.startup_status is None:
            return None
        try:
            return self.startup_status()
        except Exception:  # pragma: no cover - a launcher's bug must not break readiness
            log.exception("the start-up status hook failed")
            return None

    def lookup(self, name: str, version: str | None, build: bool = True):
        """The bundle a name and a version or alias (None: latest) name: built (``build``) or the
        registry's verified entry (manifest and path; no model built). ProblemError otherwise."""
        try:
            check_name(name)
        except BundleError as exc:
            raise ProblemError(422, str(exc), "name") from None
        if version is not None:
            try:
                check_version_ref(version)
            except BundleError as exc:
                raise ProblemError(422, str(exc), "version") from None
        try:
            return self.registry.get(name, version) if build else self.registry.entry(name, version)
        except KeyError as exc:
            startup = self.startup() or {}
            if name not in self.registry.bundles and name in [*startup.get("building", []),
                                                               *startup.get("pending", [])]:
                raise ProblemError(503, f"model {name!r} is still being built at start-up (see /health/ready); "
                                        f"retry after {self.settings.retry_after} s", "name",
                                   headers={"Retry-After": str(self.settings.retry_after)}) from None
            msg = str(exc.args[0] if exc.args else "not found")
            msg = msg.replace(str(self.registry.root).rstrip("/") + "/", "")  # paths inside the registry only
            raise ProblemError(404, msg, "version" if name in self.registry.bundles else "name") from None

    async def alookup(self, name: str, version: str | None):
        """``lookup`` that builds a model not yet in memory on a thread (the event loop keeps serving)."""
        if self.registry.is_built(name, version):
            return self.lookup(name, version)
        return await asyncio.to_thread(self.lookup, name, version)

    async def run(self, fn, *args, request: Request | None = None, token: CancelToken | None = None):
        """Run ``fn(*args)`` on the worker pool under the request deadline; cancel it if the client goes.

        ``token`` (the caller passes it to ``fn`` too) is set when a running job must stop.
        """
        timeout = self.settings.request_timeout or None
        watch = (lambda: _client_gone(request)) if request is not None else None
        try:
            return await self.executor.run(fn, *args, timeout=timeout, watch=watch, token=token)
        except QueueTimeout:
            self.metrics.timed_out.labels("queued").inc()
            raise ProblemError(503, f"the service is busy: the request waited its whole time limit of {timeout:g} s "
                                    f"(GPNARX_REQUEST_TIMEOUT) for a worker; retry after {self.settings.retry_after} s",
                               headers={"Retry-After": str(self.settings.retry_after)}, limit=timeout) from None
        except Overloaded as exc:
            self.metrics.shed.inc()
            raise ProblemError(503, f"the service is busy ({exc}); retry after {self.settings.retry_after} s",
                               headers={"Retry-After": str(self.settings.retry_after)}) from None
        except TimedOut:
            self.metrics.timed_out.labels("running").inc()
            raise ProblemError(504, f"the request did not finish within its time limit of {timeout:g} s "
                                    f"(GPNARX_REQUEST_TIMEOUT); send fewer mc_paths, a shorter record or "
                                    f"method 'linear'", "mc_paths", limit=timeout) from None
        except Abandoned as exc:
            self.metrics.abandoned.inc()
            raise ProblemError(499, f"{exc}; the job was cancelled") from None


async def _client_gone(request: Request) -> None:
    """Completes when the client disconnects (the body has already been read)."""
    while True:
        message = await request.receive()
        if message["type"] == "http.disconnect":
            return


# ------------------------------------------------------------------------------------------ middleware
class _BodyTooLarge(Exception):
    pass


class GuardMiddleware:
    """Outermost ASGI layer: API key, body-size cap, metrics, and the last-resort 500 problem."""

    def __init__(self, app, state: ServiceState, fastapi_app: FastAPI):
        self.app = app
        self.state = state
        self.fastapi_app = fastapi_app

    def _route_label(self, scope) -> str:
        route = scope.get("route")
        if route is not None and getattr(route, "path", None):
            return route.path
        for r in self.fastapi_app.router.routes:
            try:
                match, _ = r.matches(scope)
            except Exception:  # pragma: no cover
                continue
            if match == Match.FULL:
                return getattr(r, "path", "unmatched")
        return "unmatched"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        st = self.state
        t0 = time.perf_counter()
        ctx = {"status": None, "exceeded": False, "swallow": False}
        limit = st.settings.max_body_bytes
        received = 0

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                if ctx["exceeded"]:
                    ctx["swallow"] = True
                    return
                ctx["status"] = message["status"]
            elif ctx["swallow"]:
                return
            await send(message)

        async def receive_wrapper():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    ctx["exceeded"] = True
                    raise _BodyTooLarge()
            return message

        async def reply(p: ProblemError):
            resp = problem_response(p)
            ctx["status"] = p.status
            await resp(scope, receive, send)

        too_large = ProblemError(413, f"the request body exceeds the limit of {limit} bytes", "body", limit=limit)
        try:
            path = scope.get("path", "")
            headers = {}
            for k, v in scope.get("headers", []):
                headers.setdefault(k.decode("latin-1").lower(), v.decode("latin-1"))
            if st.settings.api_key and (path == "/v1" or path.startswith("/v1/")):
                given = headers.get(API_KEY_HEADER.lower(), "")
                if not given or not hmac.compare_digest(given.encode("utf-8", "replace"),
                                                        st.settings.api_key.encode("utf-8")):
                    await reply(ProblemError(401, f"a valid API key is required in the {API_KEY_HEADER} header",
                                             API_KEY_HEADER,
                                             headers={"WWW-Authenticate": f'ApiKey header="{API_KEY_HEADER}"'}))
                    return
            cl = headers.get("content-length")
            if cl is not None:
                try:
                    n = int(cl)
                    if n < 0:
                        raise ValueError
                except ValueError:
                    await reply(ProblemError(400, "the Content-Length header is not a non-negative integer",
                                             "Content-Length"))
                    return
                if n > limit:
                    await reply(too_large)
                    return
            try:
                await self.app(scope, receive_wrapper, send_wrapper)
            except _BodyTooLarge:
                pass
            if ctx["exceeded"] and (ctx["status"] is None or ctx["swallow"]):
                ctx["swallow"] = False
                await reply(too_large)
        except Exception as exc:  # last resort: never a stack trace or a bare 500
            incident = uuid.uuid4().hex[:12]
            log.exception("unhandled error (incident %s) on %s %s", incident, scope.get("method"), scope.get("path"))
            if ctx["exceeded"] and not ctx["status"]:
                await reply(too_large)
            elif ctx["status"] is None:
                await reply(ProblemError(500, f"internal error (incident {incident}); the error was logged",
                                         incident=incident))
            del exc
        finally:
            label = self._route_label(scope)
            status = ctx["status"] or 500
            st.metrics.observe(scope.get("method", "GET"), label, status, time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------ app
NameP = Annotated[str, PathParam(description="Model name (1-64 of letters, digits, '_', '-', '.').",
                                 pattern=NAME_PATTERN, max_length=64)]
VersionP = Annotated[str, PathParam(description="Model version (a positive integer) or alias (`latest`, or one an "
                                                "operator set with `gpnarx alias set`, e.g. `production`).",
                                    pattern=VERSION_PATTERN)]

_RECORD_PROBLEMS = {400: "Body is not JSON", 401: "API key missing or wrong (when GPNARX_API_KEY is set)",
                    404: "Unknown model or version", 413: "Record, Monte Carlo work or body too large",
                    422: "Invalid request (field named in `field`)", 503: "Busy: retry after Retry-After seconds",
                    504: "The request exceeded its time limit (GPNARX_REQUEST_TIMEOUT) while computing"}


def _api_description() -> str:
    b = DEFAULT_BOUNDS
    return (
        "Free-run prediction with Monte Carlo 99% bands, restoring-force loops and bolt-loosening novelty "
        "scores from GP-NARX surrogates (Teloli et al., MSSP 159 (2021) 107751).\n\n"
        "Errors are RFC 9457 problem details (`application/problem+json`) with `type`, `title`, `status`, "
        "`detail` and the offending `field`.\n\n"
        "Bounds (defaults; environment variable in brackets):\n\n"
        f"- samples per record: {b['max_samples']} [GPNARX_MAX_SAMPLES] -> 413 `u`\n"
        f"- records per batch: {b['max_batch']} [GPNARX_MAX_BATCH] -> 413 `requests`\n"
        f"- Monte Carlo paths: default {b['mc_paths_default']}, max {b['mc_paths_max']} "
        f"[GPNARX_MC_PATHS_DEFAULT, GPNARX_MC_PATHS_MAX] -> 422 `mc_paths`\n"
        f"- Monte Carlo work per HTTP request (mc_paths x samples, shared by a batch): {b['max_mc_work']} "
        f"path-steps [GPNARX_MAX_MC_WORK] -> 413 `mc_paths`\n"
        f"- body size: {b['max_body_bytes']} bytes [GPNARX_MAX_BODY_BYTES] -> 413 `body`\n"
        "- work queue: GPNARX_WORKERS running + GPNARX_QUEUE_SIZE waiting jobs -> 503 with Retry-After\n"
        f"- time per compute request (queue wait included): {DEFAULT_REQUEST_TIMEOUT:g} s "
        "[GPNARX_REQUEST_TIMEOUT, 0 = none] -> 504 if the job was running (it is cancelled), 503 with "
        "Retry-After if it was still queued; a client that disconnects cancels its job\n\n"
        "Authentication: off by default. When GPNARX_API_KEY is set, every /v1 route needs the header "
        "`X-API-Key` (401 otherwise); /health/* and /metrics stay open.\n\n"
        "Pages served with the API, from the service's own files (they work offline): /ui (models, "
        "training reports, a record's prediction, PSD, loops and novelty verdict, through this API), "
        "/docs (Swagger UI) and /redoc (ReDoc)."
    )


def limit_blas_threads(n: int) -> None:
    """Limit BLAS to ``n`` threads in this process (0: leave it); see ``service.settings``."""
    if n and not limit_blas(n):  # pragma: no cover - threadpoolctl comes with scikit-learn
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

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state.loop = asyncio.get_running_loop()
        if settings.sighup_reload and hasattr(signal, "SIGHUP"):
            loop = asyncio.get_running_loop()

            def _on_hup():
                log.info("SIGHUP: reloading the registry")
                loop.create_task(_safe_reload())

            async def _safe_reload():
                try:
                    await state.reload()
                except Exception:  # pragma: no cover
                    log.exception("reload on SIGHUP failed")

            try:
                loop.add_signal_handler(signal.SIGHUP, _on_hup)
            except (RuntimeError, ValueError, NotImplementedError):  # not the main thread
                log.info("SIGHUP reload not available in this process")
        poller = None
        if settings.registry_poll > 0 and state.registry_dir is not None:
            poller = asyncio.get_running_loop().create_task(_poll(settings.registry_poll))
        try:
            yield
        finally:
            if poller is not None:
                poller.cancel()
            state.loop = None
            state.executor.shutdown()

    async def _poll(every: float):
        """Rescan the registry every ``every`` seconds (new versions, aliases, changed or removed objects)."""
        while True:
            await asyncio.sleep(every)
            try:
                await state.reload(poll=True)
            except ProblemError as exc:  # store unreachable: the last good registry keeps serving
                log.warning("registry poll: %s", exc.detail)
            except Exception:  # pragma: no cover - a poll must never stop polling
                log.exception("registry poll failed")

    # /docs and /redoc are served by service.ui from vendored assets (no CDN: they work offline)
    app = FastAPI(title=API_TITLE, version="1", description=_api_description(), lifespan=lifespan,
                  default_response_class=JSONBytesResponse, docs_url=None, redoc_url=None)
    app.state.service = state

    # ---------------------------------------------------------------- exception handlers
    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        return problem_response(exc)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        return problem_response(validation_problem(list(exc.errors())))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        status = exc.status_code
        field = None
        if status == 404:
            detail = f"no such endpoint: {request.url.path[:200]} (see /openapi.json)"
        elif status == 405:
            detail = f"method {request.method} is not allowed on {request.url.path[:200]}"
        elif status == 400:
            detail, field = "the request body could not be read as JSON", "body"
        else:
            detail = str(exc.detail)
        return problem_response(ProblemError(status, detail, field, headers=dict(exc.headers or {})))

    @app.exception_handler(Exception)
    async def _unhandled(request: Request, exc: Exception):  # backstop; GuardMiddleware catches first
        log.error("unhandled error on %s %s: %r", request.method, request.url.path, exc)
        return problem_response(ProblemError(500, "internal error; the error was logged"))

    # ---------------------------------------------------------------- health, metrics
    @app.get("/health/live", response_model=Live, tags=["health"], operation_id="health_live",
             summary="Liveness: the process answers")
    async def health_live():
        return JSONBytesResponse({"status": "alive"})

    @app.get("/health/ready", response_model=Ready, tags=["health"], operation_id="health_ready",
             summary="Readiness: at least one bundle is loaded (lists refused bundles and start-up builds)",
             responses={503: {"description": "No bundle loaded (refused bundles listed in `refused`, bundles "
                                             "still being built at start-up in `startup`)"}})
    async def health_ready():
        n = state.n_bundles()
        startup = state.startup()
        extra = {} if startup is None else {"startup": startup}
        if n == 0:
            building = [*(startup or {}).get("building", []), *(startup or {}).get("pending", [])]
            raise ProblemError(503, "no model bundle is loaded" + (
                f"; {len(state.registry.refused)} refused (see `refused`)" if state.registry.refused else "") + (
                f"; building {', '.join(building)} (see `startup`)" if building else "") + (
                f"; the registry could not be read: {state.registry_error}" if state.registry_error else ""),
                bundles=0, refused=state.refused(), headers={"Retry-After": str(settings.retry_after)}, **extra)
        return JSONBytesResponse({"status": "ready", "bundles": n, "models": state.models(),
                                  "refused": state.refused(), **extra})

    @app.get("/metrics", tags=["health"], operation_id="metrics", summary="Prometheus metrics",
             response_class=Response, responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                                      "description": "Prometheus text exposition format"}})
    async def metrics():
        body, content_type = state.metrics.render()
        return Response(body, media_type=content_type)

    # ---------------------------------------------------------------- models
    def lags_of(m: dict) -> dict:
        return {"ny": int(m["lags"]["ny"]), "nu": int(m["lags"]["nu"])}

    def summary_of(reg, name: str) -> dict:
        b = reg.entry(name)  # the manifest: listing models builds none
        m = b.manifest
        return {"name": name, "versions": reg.versions(name), "latest": b.version, "fs": b.fs,
                "units": m.get("units") or {}, "lags": lags_of(m), "novelty": isinstance(m.get("novelty"), dict)}

    def detail_of(b) -> dict:
        m = b.manifest
        return {"name": b.name, "version": b.version, "versions": state.registry.versions(b.name),
                "aliases": state.registry.aliases_of(b.name),
                "created": m.get("created"), "lags": lags_of(m), "mode": m.get("mode"),
                "fs": b.fs, "units": m.get("units") or {}, "kernel": m.get("kernel") or {},
                "hyperparameters": m.get("hyperparameters") or {},
                "noise_calibration": m.get("noise_calibration"), "n_train": m.get("n_train"),
                "training": m.get("training") or {}, "novelty": m.get("novelty"), "physics": m.get("physics") or {},
                "package_versions": m.get("package_versions") or {},
                "probe": (m.get("novelty") or {}).get("probe") if isinstance(m.get("novelty"), dict) else None}

    v1 = "/v1"
    tags = ["models"]

    @app.get(f"{v1}/models", response_model=ModelList, tags=tags, operation_id="list_models",
             summary="List the loaded models", responses={401: {"description": _RECORD_PROBLEMS[401]}})
    async def list_models():
        reg = state.registry
        return JSONBytesResponse({"models": [summary_of(reg, n) for n in reg.names()]})

    @app.get(f"{v1}/models/{{name}}", response_model=ModelDetail, tags=tags, operation_id="get_model",
             summary="Metadata of a model's latest version (lags, fs, units, kernel, training metrics, novelty)",
             responses={k: {"description": _RECORD_PROBLEMS[k]} for k in (401, 404)})
    async def get_model(name: NameP):
        return JSONBytesResponse(detail_of(state.lookup(name, None, build=False)))

    @app.get(f"{v1}/models/{{name}}/versions/{{version}}", response_model=ModelDetail, tags=tags,
             operation_id="get_model_version", summary="Metadata of one version of a model",
             responses={k: {"description": _RECORD_PROBLEMS[k]} for k in (401, 404)})
    async def get_model_version(name: NameP, version: VersionP):
        return JSONBytesResponse(detail_of(state.lookup(name, version, build=False)))

    # ---------------------------------------------------------------- operations
    def timed_compute(plan, body, submitted, token):
        started = time.perf_counter()
        out, steps = ops.compute(plan, body, token)
        return out, steps, started - submitted, time.perf_counter() - started

    async def single(request: Request, operation: str, body: RecordRequest, name: str, version: str | None):
        bundle = await state.alookup(name, version)
        plan = ops.plan(operation, body, bundle, settings)
        token = CancelToken()
        out, steps, waited, computed = await state.run(timed_compute, plan, body, time.perf_counter(), token,
                                                       request=request, token=token)
        state.metrics.path_steps.inc(steps)
        state.metrics.answered(operation, out)
        return JSONBytesResponse(out, headers={
            "Server-Timing": f"queue;dur={waited * 1e3:.2f}, compute;dur={computed * 1e3:.2f}"})

    op_problems = {k: {"description": v} for k, v in _RECORD_PROBLEMS.items()}
    loops_problems = {**op_problems, 409: {"description": "The bundle has no physical constants (mass)"}}
    novelty_problems = {**op_problems, 409: {"description": "The bundle has no novelty calibration"}}
    ptags = ["predict"]

    @app.post(f"{v1}/models/{{name}}/predict", response_model=PredictResponse, tags=ptags, operation_id="predict",
              summary="Free-run prediction with a Monte Carlo band (latest version)", responses=op_problems)
    async def predict(request: Request, name: NameP, body: RecordRequest):
        return await single(request, "predict", body, name, None)

    @app.post(f"{v1}/models/{{name}}/versions/{{version}}/predict", response_model=PredictResponse, tags=ptags,
              operation_id="predict_version", summary="Free-run prediction with one version", responses=op_problems)
    async def predict_version(request: Request, name: NameP, version: VersionP, body: RecordRequest):
        return await single(request, "predict", body, name, version)

    @app.post(f"{v1}/models/{{name}}/loops", response_model=LoopsResponse, tags=ptags, operation_id="loops",
              summary="Restoring-force loops of the predicted response and its band (latest version)",
              responses=loops_problems)
    async def loops(request: Request, name: NameP, body: RecordRequest):
        return await single(request, "loops", body, name, None)

    @app.post(f"{v1}/models/{{name}}/versions/{{version}}/loops", response_model=LoopsResponse, tags=ptags,
              operation_id="loops_version", summary="Restoring-force loops with one version",
              responses=loops_problems)
    async def loops_version(request: Request, name: NameP, version: VersionP, body: RecordRequest):
        return await single(request, "loops", body, name, version)

    @app.post(f"{v1}/models/{{name}}/novelty", response_model=NoveltyResponse, tags=ptags, operation_id="novelty",
              summary="Novelty score, threshold and verdict of a measured record (latest version)",
              responses=novelty_problems)
    async def novelty(request: Request, name: NameP, body: NoveltyRequest):
        return await single(request, "novelty", body, name, None)

    @app.post(f"{v1}/models/{{name}}/versions/{{version}}/novelty", response_model=NoveltyResponse, tags=ptags,
              operation_id="novelty_version", summary="Novelty score with one version", responses=novelty_problems)
    async def novelty_version(request: Request, name: NameP, version: VersionP, body: NoveltyRequest):
        return await single(request, "novelty", body, name, version)

    # ---------------------------------------------------------------- batch
    @app.post(f"{v1}/batch", response_model=BatchResponse, tags=ptags, operation_id="batch",
              summary="Many records: each answered or failed on its own, in order",
              responses={**{k: {"description": _RECORD_PROBLEMS[k]} for k in (400, 401, 413, 422, 503, 504)},
                         415: {"description": "Body is not application/json"}},
              openapi_extra={"requestBody": {"required": True, "content": {"application/json": {
                  "schema": {"$ref": "#/components/schemas/BatchRequest"}}}}})
    async def batch(request: Request):
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
                    out, s = ops.compute(plan, req, token)
                    steps += s
                    done.append((i, out))
                    state.metrics.answered(plan.operation, out)
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
            done, steps = await state.run(run_all, token, request=request, token=token)
            state.metrics.path_steps.inc(steps)
            for i, out in done:
                results[i] = out
        return JSONBytesResponse({"results": results})

    # ---------------------------------------------------------------- admin
    @app.post(f"{v1}/admin/reload", response_model=ReloadResponse, tags=["admin"], operation_id="reload",
              summary="Rescan the registry (in-flight requests keep their bundle)",
              responses={401: {"description": _RECORD_PROBLEMS[401]},
                         409: {"description": "No registry folder configured"}})
    async def reload():
        return JSONBytesResponse(await state.reload())

    # ---------------------------------------------------------------- page, docs, reports, record files
    ui.install(app, state, JSONBytesResponse)

    app.add_middleware(GuardMiddleware, state=state, fastapi_app=app)
    state.metrics.update_bundles()

    def custom_openapi():
        if app.openapi_schema is None:
            app.openapi_schema = build_openapi(app)
        return app.openapi_schema

    app.openapi = custom_openapi
    return app


# ------------------------------------------------------------------------------------------ OpenAPI
def _component_schemas(model) -> dict:
    schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
    defs = schema.pop("$defs", {})
    return {model.__name__: schema, **defs}


def build_openapi(app: FastAPI) -> dict:
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
    doc["components"]["securitySchemes"] = {"ApiKeyAuth": {
        "type": "apiKey", "in": "header", "name": API_KEY_HEADER,
        "description": "Required on /v1 routes only when the server sets GPNARX_API_KEY."}}
    problem_ref = {"schema": {"$ref": "#/components/schemas/Problem"}}
    for path, item in doc.get("paths", {}).items():
        for op in item.values():
            responses = op.setdefault("responses", {})
            responses.setdefault("500", {"description": "Internal error (a problem detail, never a stack trace)"})
            for code, resp in responses.items():
                if code.isdigit() and int(code) >= 400:
                    resp["content"] = {PROBLEM_MEDIA_TYPE: problem_ref}
                    if code == "422":
                        resp["description"] = _RECORD_PROBLEMS[422]
            if path.startswith("/v1/"):
                op["security"] = [{}, {"ApiKeyAuth": []}]
    return doc


def openapi_document() -> dict:
    """The OpenAPI document of the service with default settings (what ``openapi/openapi.json`` holds)."""
    return create_app(None, Settings(workers=1, queue_size=0)).openapi()


def openapi_json() -> str:
    """``openapi_document()`` as committed: sorted keys, indent 2, trailing newline."""
    return json.dumps(openapi_document(), sort_keys=True, indent=2, ensure_ascii=False) + "\n"
