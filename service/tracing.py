"""Optional OpenTelemetry tracing (``GPNARX_OTEL``; extra ``otel``).

``off`` (the default) imports nothing of OpenTelemetry (FastAPI imports ``opentelemetry-api``, its own
dependency; the SDK, instrumentation and exporters of the extra are never imported), so the core install
does not need the extra.
``console`` writes each finished span as one JSON line to stderr (stdout may carry the audit trail);
``otlp`` sends spans over OTLP/HTTP to ``OTEL_EXPORTER_OTLP_TRACES_ENDPOINT`` or
``OTEL_EXPORTER_OTLP_ENDPOINT`` (default ``http://localhost:4318``), the exporter's standard variables.
The service name is ``gpnarx`` unless ``OTEL_SERVICE_NAME`` / ``OTEL_RESOURCE_ATTRIBUTES`` say otherwise.

``instrument(app, mode)`` builds the app's own tracer provider (``app.state.tracer_provider``; no
process-global provider is set, so several apps in one process do not collide), instruments the
FastAPI app with it (one server span per request, named ``METHOD route``, with ``http.route``) and
adds ``SpanAttributes``, which puts the request's ``X-Request-ID`` (``gpnarx.request_id``) and the
model of a ``/v1/models/{name}/...`` route (``gpnarx.model``, ``gpnarx.model_version``) on that span.
The app's lifespan shuts the provider down, which sends the spans still queued.
"""
from __future__ import annotations

import os
import re
import sys

OTEL_MODES = ("off", "console", "otlp")
INSTALL_HINT = "pip install 'gpnarx[otel]'"
SERVICE_NAME = "gpnarx"
ATTR_REQUEST_ID = "gpnarx.request_id"
ATTR_MODEL = "gpnarx.model"
ATTR_MODEL_VERSION = "gpnarx.model_version"
_MODEL_PATH = re.compile(r"^/v1/models/([^/]+)(?:/versions/([^/]+))?")


def _import_error(mode: str, exc: ImportError) -> ImportError:
    missing = getattr(exc, "name", None) or str(exc)
    return ImportError(f"GPNARX_OTEL={mode} needs the OpenTelemetry packages ({missing} is not installed): "
                       f"{INSTALL_HINT}")


def tracer_provider(mode: str):
    """A ``TracerProvider`` exporting to ``mode`` (``console`` or ``otlp``) through a batch processor."""
    if mode not in OTEL_MODES or mode == "off":
        raise ValueError(f"tracing mode must be one of {OTEL_MODES[1:]}, got {mode!r}")
    try:
        from opentelemetry.sdk.resources import Resource
        from opentelemetry.sdk.trace import TracerProvider
        from opentelemetry.sdk.trace.export import BatchSpanProcessor, ConsoleSpanExporter

        if mode == "otlp":
            from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter
    except ImportError as exc:
        raise _import_error(mode, exc) from None
    from gpnarx import __version__

    resource = Resource.create({"service.name": os.environ.get("OTEL_SERVICE_NAME") or SERVICE_NAME,
                                "service.version": __version__})
    provider = TracerProvider(resource=resource)
    if mode == "otlp":
        exporter = OTLPSpanExporter()
    else:  # one line per span on stderr: stdout is the audit trail's default target
        exporter = ConsoleSpanExporter(out=sys.stderr, formatter=lambda span: span.to_json(indent=None) + "\n")
    provider.add_span_processor(BatchSpanProcessor(exporter))
    return provider


class SpanAttributes:
    """ASGI middleware (outside ``GuardMiddleware``): request id and model on the request's server span.

    Set when the answer starts (the span ends with the answer's last body message), from the scope
    the inner layers filled in: the id ``GuardMiddleware`` accepted or generated and Starlette's path
    parameters, or the path itself for a request answered before routing (401, 503, 413)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        from opentelemetry import trace

        span = trace.get_current_span()

        async def send_with_attributes(message):
            if message["type"] == "http.response.start" and span.is_recording():
                span.set_attributes(request_attributes(scope))
            await send(message)

        await self.app(scope, receive, send_with_attributes)


def request_attributes(scope) -> dict:
    """``gpnarx.request_id``, ``gpnarx.model`` and ``gpnarx.model_version`` of an answered request's scope."""
    out = {}
    rid = (scope.get("state") or {}).get("request_id")
    if rid:
        out[ATTR_REQUEST_ID] = rid
    params = scope.get("path_params") or {}
    name, version = params.get("name"), params.get("version")
    if name is None:
        m = _MODEL_PATH.match(scope.get("path", ""))
        if m:
            name, version = m.group(1), m.group(2)
    if name:
        out[ATTR_MODEL] = str(name)
    if version:
        out[ATTR_MODEL_VERSION] = str(version)
    return out


def instrument(app, mode: str):
    """Trace ``app`` to ``mode`` (see the module); returns the tracer provider. ImportError naming
    ``pip install 'gpnarx[otel]'`` when the extra is not installed."""
    provider = tracer_provider(mode)
    try:
        from opentelemetry.instrumentation.fastapi import FastAPIInstrumentor
    except ImportError as exc:
        raise _import_error(mode, exc) from None
    app.add_middleware(SpanAttributes)
    # no child spans per ASGI send/receive message: one server span per request
    FastAPIInstrumentor.instrument_app(app, tracer_provider=provider, exclude_spans=["receive", "send"])
    app.state.tracer_provider = provider
    return provider
