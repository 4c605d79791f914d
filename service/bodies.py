"""Large request bodies parsed and validated off the event loop.

Parsing and validating a JSON record of a few MB takes tens to hundreds of milliseconds of CPU; on
the event loop that time stalls every other connection (``/health/live`` included). A body of at
least ``OFF_LOOP_BYTES`` bytes is therefore handled on a worker thread
(``starlette.concurrency.run_in_threadpool``), a smaller one inline (a thread hop costs more than it
saves). The record routes (``routers.predict.RecordRoute``) and the batch route
(``routers.batch``) both go through ``off_loop``.
"""
from __future__ import annotations

from typing import Callable, TypeVar

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from .responses import parse_json

#: JSON bodies at least this long [bytes] are parsed and validated on a thread, off the event loop (a flood of
#: large bodies then never stalls the loop, so /health/live and small requests keep answering)
OFF_LOOP_BYTES = 64 * 1024

T = TypeVar("T")


def declared_length(request: Request) -> int:
    """The request's Content-Length [bytes] (0 when absent or not a number)."""
    try:
        return int(request.headers.get("content-length", "0"))
    except ValueError:
        return 0


def is_large(size: int) -> bool:
    """Whether a body of ``size`` bytes is handled off the event loop."""
    return size >= OFF_LOOP_BYTES


async def off_loop(size: int, fn: Callable[..., T], *args) -> T:
    """``fn(*args)`` on a worker thread when the body is large (``is_large(size)``), else inline."""
    if is_large(size):
        return await run_in_threadpool(fn, *args)
    return fn(*args)


def parse_or_none(raw: bytes):
    """The JSON value of ``raw``, or None when it does not parse."""
    try:
        return parse_json(raw)
    except ValueError:
        return None


def validated(model, fields):
    """``fields`` validated by the body ``model``; FastAPI's ``RequestValidationError`` (located in the body)
    otherwise."""
    try:
        return model.model_validate(fields)
    except ValidationError as exc:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in exc.errors()]) from None
