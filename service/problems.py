"""RFC 9457 problem details (``application/problem+json``).

Every error the service returns is a JSON object with ``type``, ``title``, ``status``, ``detail``
and, when one request field is to blame, ``field`` (a dotted path into the request body, e.g.
``u``, ``mc_paths`` or ``requests.2.mc_paths``; path parameters are named ``name``/``version``).
Inside a request every problem also carries ``request_id`` (the request's ``X-Request-ID``,
``service.observability``).
Validation errors also carry ``errors``: one ``{field, message, type}`` per problem found. A
stack trace is never returned.
"""
from __future__ import annotations

from collections.abc import Iterable
from http import HTTPStatus
from typing import Any

from .observability import REQUEST_ID

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_BASE = "https://gpnarx.dev/problems/"

#: problem ``type`` slug per HTTP status (an unknown status falls back to about:blank).
SLUGS = {
    400: "bad-request",
    401: "unauthorized",
    404: "not-found",
    405: "method-not-allowed",
    408: "request-timeout",
    409: "conflict",
    413: "too-large",
    415: "unsupported-media-type",
    422: "invalid-request",
    500: "internal-error",
    499: "client-closed-request",
    503: "overloaded",
    504: "timeout",
}


def title_for(status: int) -> str:
    if status == 499:  # not in http.HTTPStatus (nginx's code; the client never reads it)
        return "Client Closed Request"
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


#: longest message of one validation error, and of a problem's detail [characters]: a message that quotes the
#: input (a 4000-digit number, a long name) stays readable
MAX_MESSAGE_CHARS = 300
MAX_DETAIL_CHARS = 600


def capped(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was."""
    if len(text) <= limit:
        return text
    return text[: limit - 25] + f"... ({len(text)} characters)"


class ProblemError(Exception):
    """Raised anywhere in the service; turned into a problem-details response."""

    def __init__(self, status: int, detail: str, field: str | None = None, *, title: str | None = None,
                 type_: str | None = None, headers: dict | None = None, **extra: Any):
        detail = capped(str(detail), MAX_DETAIL_CHARS)
        super().__init__(detail)
        self.status = int(status)
        self.detail = detail
        self.field = field
        self.title = title or title_for(self.status)
        self.type = type_ or (TYPE_BASE + SLUGS[self.status] if self.status in SLUGS else "about:blank")
        self.headers = headers or {}
        self.extra = extra

    def to_dict(self, field_prefix: str | None = None) -> dict:
        field = self.field
        if field_prefix is not None:
            field = field_prefix if not field else f"{field_prefix}.{field}"
        d = {"type": self.type, "title": self.title, "status": self.status, "detail": self.detail,
             "field": field}
        for k, v in self.extra.items():
            if k == "errors" and field_prefix is not None and isinstance(v, list):
                v = [{**e, "field": f"{field_prefix}.{e['field']}" if e.get("field") else field_prefix} for e in v]
            d[k] = v
        rid = REQUEST_ID.get()
        if rid is not None and "request_id" not in d:  # the request's X-Request-ID (service.observability)
            d["request_id"] = rid
        return d


def loc_to_field(loc: Iterable) -> str | None:
    """Pydantic/FastAPI error location -> dotted field path (``('body', 'u', 3)`` -> ``u.3``)."""
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "path", "query", "header", "cookie"):
        kind = parts[0]
        parts = parts[1:]
        if not parts:
            return "body" if kind == "body" else None
    # pydantic adds tags for unions/function validators (e.g. 'function-after[...]'); drop them
    parts = [p for p in parts if "[" not in p]
    return ".".join(parts) or None


def _message(err: dict) -> str:
    msg = str(err.get("msg", "invalid value"))
    ctx = err.get("ctx") or {}
    if err.get("type") == "json_invalid" and ctx.get("error"):
        msg = f"request body is not valid JSON: {ctx['error']}"
    return capped(msg, MAX_MESSAGE_CHARS)


def validation_problem(errors: list[dict], status: int = 422) -> ProblemError:
    """One problem detail for a list of pydantic/FastAPI validation errors."""
    items = []
    for err in errors:
        field = "body" if err.get("type") == "json_invalid" else loc_to_field(err.get("loc", ()))
        items.append({"field": field, "message": _message(err), "type": str(err.get("type", "value_error"))})
    if not items:
        items.append({"field": None, "message": "invalid request", "type": "value_error"})
    first = items[0]
    if any(e["type"] == "json_invalid" for e in items):
        return ProblemError(400, first["message"], "body", errors=items)
    if first["field"]:
        detail = f"{first['field']}: {first['message']}"
    else:
        detail = first["message"]
    if len(items) > 1:
        detail += f" (and {len(items) - 1} more error{'s' if len(items) > 2 else ''})"
    return ProblemError(status, detail, first["field"], errors=items)


#: JSON schema of a problem detail, for the OpenAPI document.
PROBLEM_EXAMPLE = {
    "type": TYPE_BASE + "invalid-request",
    "title": "Unprocessable Content",
    "status": 422,
    "detail": "mc_paths: 10000 exceeds the limit of 4096 Monte Carlo paths",
    "field": "mc_paths",
}
