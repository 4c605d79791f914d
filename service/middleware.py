"""The outermost ASGI layer: API key, body-size cap, request metrics and the last-resort 500 problem.

With ``GPNARX_API_KEY`` set, a request to a ``/v1`` path without the key is answered 401 from its
headers alone, before any body byte is read or parsed (so unauthenticated requests cost no memory
beyond their headers), and a request to an open path (health, metrics, pages) may carry at most
``UNAUTHENTICATED_BODY_BYTES``. The key is also a route dependency
(``service.deps.require_api_key``), so OpenAPI documents it.
"""
from __future__ import annotations

import asyncio
import logging
import time
import uuid
import zlib

from fastapi import FastAPI
from starlette.routing import Match

from .deps import API_KEY_HEADER, key_problem
from .observability import REQUEST_ID, REQUEST_ID_HEADER, request_id_for
from .problems import ProblemError
from .responses import problem_response
from .state import ServiceState

log = logging.getLogger("gpnarx.service")

#: body cap [bytes] of a request to an open path (no key needed there) when an API key is set
UNAUTHENTICATED_BODY_BYTES = 64 * 1024


_COMPUTE = ("/predict", "/loops", "/novelty")


def is_compute(scope) -> bool:
    """A request whose answer runs on the worker pool (predict, loops, novelty, batch)."""
    path = scope.get("path", "")
    return scope.get("method") == "POST" and (path == "/v1/batch" or (path.startswith("/v1/models/")
                                                                      and path.endswith(_COMPUTE)))


def needs_key(path: str) -> bool:
    """Whether ``path`` is under ``/v1`` (every ``/v1`` route needs the key when one is set)."""
    return path == "/v1" or path.startswith("/v1/")


def _header(scope, name: bytes) -> str | None:
    """The first value of header ``name`` (lower case) of an ASGI scope, or None."""
    for k, v in scope.get("headers") or ():
        if k.lower() == name:
            return v.decode("latin-1")
    return None


class _BodyTooLarge(Exception):
    pass


#: request bodies the service decodes (``Content-Encoding``); anything else is a 415
REQUEST_ENCODINGS = ("gzip", "identity")


def _request_encoding(scope) -> str | None:
    """The request's body encoding ('gzip' or None for none/identity); ProblemError 415 for another one."""
    value = _header(scope, b"content-encoding")
    codings = [c.strip().lower() for c in (value or "").split(",") if c.strip()]
    codings = [c for c in codings if c != "identity"]
    if not codings:
        return None
    if codings == ["gzip"] or codings == ["x-gzip"]:
        return "gzip"
    raise ProblemError(415, f"Content-Encoding {value[:60]!r} is not supported: send the body as it is or "
                            f"gzip-compressed (Content-Encoding: gzip)", "content-encoding",
                       accepted=list(REQUEST_ENCODINGS))


def _without_encoding(scope) -> dict:
    """``scope`` without the headers that describe the encoded body (its encoding and length)."""
    drop = (b"content-encoding", b"content-length")
    return {**scope, "headers": [(k, v) for k, v in scope.get("headers") or () if k.lower() not in drop]}


class _BodyTimeout(Exception):
    pass


def _matching_path(routes, scope, depth: int = 0) -> str | None:
    """The path template of the route among ``routes`` that fully matches ``scope``, looking into included
    routers (FastAPI wraps each in an object whose ``original_router`` holds its routes); None when none does."""
    for r in routes:
        try:
            match, _ = r.matches(scope)
        except Exception:  # pragma: no cover - a route type that cannot match this scope
            continue
        if match != Match.FULL:
            continue
        if getattr(r, "path", None):
            return r.path
        inner = getattr(getattr(r, "original_router", None), "routes", None)
        if inner and depth < 4:
            return _matching_path(inner, scope, depth + 1)
    return None


class GuardMiddleware:
    """Outermost ASGI layer: body-size cap, metrics, and the last-resort 500 problem."""

    def __init__(self, app, state: ServiceState, fastapi_app: FastAPI):
        self.app = app
        self.state = state
        self.fastapi_app = fastapi_app

    def _route_label(self, scope) -> str:
        route = scope.get("route")
        if route is not None and getattr(route, "path", None):
            return route.path
        # a request answered before routing (API key, shedding, body size, encoding): the route it was for
        return _matching_path(self.fastapi_app.router.routes, scope) or "unmatched"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        st = self.state
        t0 = time.perf_counter()
        rid = request_id_for(_header(scope, b"x-request-id"))  # echoed on every answer, in logs and problems
        scope.setdefault("state", {})["request_id"] = rid
        rid_token = REQUEST_ID.set(rid)
        rid_header = (REQUEST_ID_HEADER.lower().encode(), rid.encode())
        ctx = {"status": None, "exceeded": False, "swallow": False, "timeout": False}
        head = scope.get("method") == "HEAD"  # a GET route answers HEAD too: its headers, without the body
        if head:
            scope = {**scope, "method": "GET"}
        limit = st.settings.max_body_bytes
        key = st.settings.api_key
        if key and not needs_key(scope.get("path", "")):
            limit = min(limit, UNAUTHENTICATED_BODY_BYTES)
        received = 0

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                if ctx["exceeded"]:
                    ctx["swallow"] = True
                    return
                ctx["status"] = message["status"]
                headers = list(message.get("headers") or [])
                if not any(k.lower() == rid_header[0] for k, _ in headers):
                    message = {**message, "headers": [*headers, rid_header]}
            elif ctx["swallow"]:
                return
            elif head and message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        body_timeout = st.settings.body_timeout
        body_done = False
        inflate = None  # a gzip-encoded body: decoded here, its decoded size under the same cap

        async def receive_wrapper():
            nonlocal received, body_done
            if body_done or not body_timeout:
                message = await receive()
            else:  # the whole body within GPNARX_BODY_TIMEOUT of the request's start (a slow client is cut)
                try:
                    message = await asyncio.wait_for(receive(), max(0.0, t0 + body_timeout - time.perf_counter()))
                except asyncio.TimeoutError:
                    ctx["exceeded"] = ctx["timeout"] = True
                    raise _BodyTimeout() from None
            if message["type"] == "http.request" and not message.get("more_body", False):
                body_done = True
            if message["type"] == "http.request":
                if inflate is not None:
                    message = {**message, "body": _inflated(message)}
                received += len(message.get("body", b""))
                if received > limit:
                    ctx["exceeded"] = True
                    raise _BodyTooLarge()
            return message

        def _inflated(message) -> bytes:
            """This chunk of a gzip body decoded, at most one byte past the cap (then the cap's 413)."""
            nonlocal inflate
            try:
                out = inflate.decompress(message.get("body", b""), max(0, limit - received) + 1)
                if inflate.unconsumed_tail:  # more decoded bytes than the cap allows: the cap's 413
                    return out + b"\0"
                while inflate.eof and inflate.unused_data:  # another gzip member follows (RFC 1952)
                    rest = inflate.unused_data
                    inflate = zlib.decompressobj(wbits=31)
                    out += inflate.decompress(rest, max(0, limit - received - len(out)) + 1)
                    if inflate.unconsumed_tail:
                        return out + b"\0"
                if not message.get("more_body", False) and not inflate.eof:
                    raise zlib.error("the gzip stream ends early")
            except zlib.error as exc:  # answered as an oversized body is: the app's own answer is swallowed
                ctx["exceeded"] = True
                ctx["refusal"] = ProblemError(400, f"the gzip-encoded body could not be decoded ({exc})",
                                              "content-encoding")
                raise _BodyTooLarge() from None
            return out

        async def reply(p: ProblemError):
            resp = problem_response(p)
            ctx["status"] = p.status
            await resp(scope, receive, send)

        too_large = ProblemError(413, f"the request body exceeds the limit of {limit} bytes", "body", limit=limit)
        too_slow = ProblemError(408, f"the request body was not received within {st.settings.body_timeout:g} s "
                                     f"(GPNARX_BODY_TIMEOUT)", "body", limit=st.settings.body_timeout,
                                headers={"Connection": "close"})
        try:
            headers = {}
            for k, v in scope.get("headers", []):
                headers.setdefault(k.decode("latin-1").lower(), v.decode("latin-1"))
            if key and needs_key(scope.get("path", "")):
                problem = key_problem(key, headers.get(API_KEY_HEADER.lower()))
                if problem is not None:  # answered from the headers: the body is never read
                    await reply(problem)
                    return
            if is_compute(scope):  # shed before reading the body: a refused request costs no parsing
                problem = st.busy()
                if problem is not None:
                    await reply(problem)
                    return
            try:
                if _request_encoding(scope) == "gzip":
                    inflate = zlib.decompressobj(wbits=31)
                    scope = _without_encoding(scope)
            except ProblemError as problem:
                await reply(problem)
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
            except (_BodyTooLarge, _BodyTimeout):
                pass
            if ctx["exceeded"] and (ctx["status"] is None or ctx["swallow"]):
                ctx["swallow"] = False
                await reply(ctx.get("refusal") or (too_slow if ctx["timeout"] else too_large))
        except asyncio.CancelledError:
            # the server cancels requests still running when its drain window (GPNARX_DRAIN_TIMEOUT) ends:
            # a retryable 503 problem instead of uvicorn's bare text/plain 500
            task = asyncio.current_task()
            if task is not None:
                task.uncancel()
            if ctx["status"] is None:
                log.warning("request %s %s cancelled at shutdown; answered 503", scope.get("method"),
                            scope.get("path"))
                await reply(ProblemError(503, "the server is shutting down and stopped this request; retry, "
                                              "another replica will answer",
                                         headers={"Retry-After": str(st.settings.retry_after)}))
        except Exception as exc:  # last resort: never a stack trace or a bare 500
            incident = uuid.uuid4().hex[:12]
            log.exception("unhandled error (incident %s) on %s %s", incident, scope.get("method"), scope.get("path"))
            if ctx["exceeded"] and not ctx["status"]:
                await reply(ctx.get("refusal") or (too_slow if ctx["timeout"] else too_large))
            elif ctx["status"] is None:
                await reply(ProblemError(500, f"internal error (incident {incident}); the error was logged",
                                         incident=incident))
            del exc
        finally:
            label = self._route_label(scope)
            status = ctx["status"] or 500
            st.metrics.observe(scope.get("method", "GET"), label, status, time.perf_counter() - t0)
            REQUEST_ID.reset(rid_token)

