"""Request ids and structured logs.

``X-Request-ID``: a request may carry its own id (1 to ``REQUEST_ID_MAX`` printable ASCII characters,
no spaces); any other value, or none, is replaced by a generated one (32 hex digits). The id is
echoed on every answer, is the ``request_id`` member of every problem detail, is in every log line
written while the request is served (``REQUEST_ID``, a context variable the worker threads inherit),
and in the audit trail (``service.audit``).

Logs: ``GPNARX_LOG_FORMAT=text`` (default) writes ``time level logger [request_id] message``;
``json`` writes one JSON object per line with ``time`` (UTC, ISO 8601), ``level``, ``logger``,
``message``, ``request_id`` (null outside a request) and, for an error with a traceback,
``exc_info``. ``logging_config`` is the dict uvicorn is started with, so its own logs take the same
format.
"""
from __future__ import annotations

import json
import logging
import re
import uuid
from contextvars import ContextVar
from datetime import datetime, timezone

REQUEST_ID_HEADER = "X-Request-ID"
#: the longest request id accepted from a client [characters]
REQUEST_ID_MAX = 128
_VALID_ID = re.compile(r"[\x21-\x7e]{1,%d}" % REQUEST_ID_MAX)

#: the id of the request being served (None outside a request)
REQUEST_ID: ContextVar[str | None] = ContextVar("gpnarx_request_id", default=None)

LOG_FORMATS = ("text", "json")


def new_request_id() -> str:
    return uuid.uuid4().hex


def valid_request_id(value: str | None) -> bool:
    """Whether a client's ``X-Request-ID`` is kept: 1 to REQUEST_ID_MAX visible ASCII characters."""
    return bool(value) and _VALID_ID.fullmatch(value) is not None


def request_id_for(value: str | None) -> str:
    """The id of a request whose ``X-Request-ID`` header is ``value`` (None: absent)."""
    return value if valid_request_id(value) else new_request_id()


def current_request_id() -> str | None:
    return REQUEST_ID.get()


class RequestIdFilter(logging.Filter):
    """Puts the current request's id on every record (``record.request_id``; None outside a request)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "request_id"):
            record.request_id = REQUEST_ID.get()
        return True


def _iso(created: float) -> str:
    return datetime.fromtimestamp(created, tz=timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, request_id (+ exc_info)."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"time": _iso(record.created), "level": record.levelname, "logger": record.name,
               "message": record.getMessage(),
               "request_id": getattr(record, "request_id", None) or REQUEST_ID.get()}
        if record.exc_info:
            out["exc_info"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exc_info"] = record.exc_text
        return json.dumps(out, ensure_ascii=False, default=str)


class TextFormatter(logging.Formatter):
    """``time level logger [request_id] message``; the id part only inside a request."""

    def __init__(self):
        super().__init__("%(asctime)s %(levelname)s %(name)s%(rid)s %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        rid = getattr(record, "request_id", None) or REQUEST_ID.get()
        record.rid = f" [{rid}]" if rid else ""
        return super().format(record)


def formatter(fmt: str) -> logging.Formatter:
    if fmt not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {LOG_FORMATS}, got {fmt!r}")
    return JsonFormatter() if fmt == "json" else TextFormatter()


def logging_config(fmt: str = "text", level: str = "info") -> dict:
    """A ``logging.config.dictConfig`` dict (uvicorn's ``log_config``): the gpnarx and uvicorn
    loggers write to stderr in format ``fmt``, with the request id."""
    factory = "gpnarx.service.observability." + ("JsonFormatter" if fmt == "json" else "TextFormatter")
    if fmt not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {LOG_FORMATS}, got {fmt!r}")
    lvl = level.upper()
    handler = {"class": "logging.StreamHandler", "stream": "ext://sys.stderr", "formatter": "gpnarx",
               "filters": ["request_id"]}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "filters": {"request_id": {"()": "gpnarx.service.observability.RequestIdFilter"}},
        "formatters": {"gpnarx": {"()": factory}},
        "handlers": {"default": handler},
        "loggers": {
            "gpnarx": {"handlers": ["default"], "level": lvl, "propagate": False},
            "uvicorn": {"handlers": ["default"], "level": lvl, "propagate": False},
            "uvicorn.error": {"level": lvl},
            "uvicorn.access": {"handlers": ["default"], "level": lvl, "propagate": False},
        },
    }


def configure_logging(fmt: str = "text", level: str = "info") -> None:
    """Apply ``logging_config(fmt, level)`` to this process."""
    import logging.config

    logging.config.dictConfig(logging_config(fmt, level))
