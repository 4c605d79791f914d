"""JSON bodies of the service: fast rendering of numpy arrays, strict parsing, problem responses."""
from __future__ import annotations

import json
from typing import Any

from starlette.responses import JSONResponse, Response

from gpnarx.storage.jsonsafe import dumps_json

from .observability import REQUEST_ID, REQUEST_ID_HEADER
from .problems import PROBLEM_MEDIA_TYPE, ProblemError
from .wire import etag_of, not_modified

try:  # fast JSON for long float arrays
    import orjson as _orjson
except ImportError:  # pragma: no cover - exercised only without orjson
    _orjson = None


def render_json(obj) -> bytes:
    """JSON bytes; numpy arrays serialised natively (orjson) and non-finite floats as null."""
    return dumps_json(obj)


def parse_json(raw: bytes, non_finite: bool = False):
    """Parse a request body; ``ValueError`` with a clear message when it is not JSON.

    ``non_finite``: also take the tokens NaN, Infinity and -Infinity and numbers beyond the float range (as
    non-finite floats), for a caller that refuses them field by field (a batch: one record's bad number must
    not lose the other records); otherwise they make the body invalid.
    """
    if _orjson is not None:
        try:
            return _orjson.loads(raw)
        except _orjson.JSONDecodeError as exc:
            if not non_finite:
                raise ValueError(f"request body is not valid JSON: {exc}") from None
    try:
        return json.loads(raw, **({} if non_finite else {"parse_constant": _refuse_constant}))
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
    headers = dict(p.headers)
    rid = REQUEST_ID.get()
    if rid is not None:
        headers.setdefault(REQUEST_ID_HEADER, rid)
    return ProblemResponse(p.to_dict(), status_code=p.status, headers=headers)


def conditional(request, body: bytes, media_type: str, cache_control: str, headers: dict | None = None):
    """``body`` with an ETag and ``Cache-Control``, or a 304 when the request's ``If-None-Match`` names it.

    Behind an API key the answer is ``private`` (no shared cache keeps it).
    """
    etag = etag_of(body)
    keyed = bool(request.app.state.service.settings.api_key)
    cc = f"private, {cache_control}" if keyed else cache_control
    hdrs = {**(headers or {}), "ETag": etag, "Cache-Control": cc}
    if not_modified(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers={"ETag": etag, "Cache-Control": cc})
    return Response(body, media_type=media_type, headers=hdrs)
