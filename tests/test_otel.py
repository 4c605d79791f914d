"""Optional OpenTelemetry tracing (GPNARX_OTEL, extra ``otel``; service.tracing).

On: a predict request is one server span with its route, the request's X-Request-ID and the model.
Off (the default): gpnarx imports nothing of OpenTelemetry (FastAPI imports opentelemetry-api, its own
dependency, whatever the setting) and the app is not instrumented. Without the
extra, turning it on fails at start-up naming ``pip install 'gpnarx[otel]'``.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.tracing import ATTR_MODEL, ATTR_MODEL_VERSION, ATTR_REQUEST_ID

pytest.importorskip("opentelemetry.sdk")
pytest.importorskip("opentelemetry.instrumentation.fastapi")

from opentelemetry.sdk.trace.export import SimpleSpanProcessor  # noqa: E402
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter  # noqa: E402
from opentelemetry.trace import SpanKind  # noqa: E402


def traced_app(**kw):
    app = create_app(built_registry().root, Settings(workers=1, queue_size=4, otel="console", **kw))
    exporter = InMemorySpanExporter()
    app.state.tracer_provider.add_span_processor(SimpleSpanProcessor(exporter))
    return app, exporter


def server_spans(exporter):
    return [s for s in exporter.get_finished_spans() if s.kind == SpanKind.SERVER]


def test_predict_request_is_a_server_span_with_route_request_id_and_model(capfd):
    app, exporter = traced_app()
    u, _ = short_record(64, 3)
    with TestClient(app) as c:
        r = c.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": 8, "seed": 0},
                   headers={"X-Request-ID": "trace-me-1"})
        assert r.status_code == 200, r.text
        assert r.headers["x-request-id"] == "trace-me-1"
        r2 = c.post("/v1/models/boucwen/versions/1/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": 8})
        assert r2.status_code == 200, r2.text
        generated = r2.headers["x-request-id"]
    spans = server_spans(exporter)
    assert len(spans) == 2, [s.name for s in exporter.get_finished_spans()]  # no send/receive child spans
    first, second = spans
    assert first.name == "POST /v1/models/{name}/predict"
    assert first.attributes["http.route"] == "/v1/models/{name}/predict"
    assert first.attributes[ATTR_REQUEST_ID] == "trace-me-1"
    assert first.attributes[ATTR_MODEL] == "boucwen"
    assert ATTR_MODEL_VERSION not in first.attributes
    assert second.attributes[ATTR_REQUEST_ID] == generated
    assert (second.attributes[ATTR_MODEL], second.attributes[ATTR_MODEL_VERSION]) == ("boucwen", "1")
    assert first.resource.attributes["service.name"] == "gpnarx"
    # console mode: one JSON object per span on stderr (sent when the lifespan ends), nothing on stdout
    out, err = capfd.readouterr()
    lines = [json.loads(line) for line in err.splitlines() if line.startswith("{")]
    assert any(d["attributes"].get(ATTR_REQUEST_ID) == "trace-me-1" for d in lines), err[-2000:]
    assert "trace-me-1" not in out


PARENT = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01"


def test_a_request_answered_early_carries_its_id_and_continues_the_callers_trace():
    app, exporter = traced_app(api_key="k")
    with TestClient(app) as c:
        r = c.post("/v1/models/boucwen/predict", json={}, headers={"X-Request-ID": "no-key-1", "traceparent": PARENT})
        assert r.status_code == 401
    (span,) = server_spans(exporter)
    assert f"{span.context.trace_id:032x}" == PARENT.split("-")[1]  # the caller's trace goes on
    assert span.attributes[ATTR_REQUEST_ID] == "no-key-1"
    assert span.attributes[ATTR_MODEL] == "boucwen"
    assert span.attributes["http.response.status_code" if "http.response.status_code" in span.attributes
                           else "http.status_code"] == 401


def test_setting_is_read_from_the_environment_and_checked():
    assert Settings.from_env({"GPNARX_OTEL": "otlp"}).otel == "otlp"
    assert Settings.from_env({}).otel == "off"
    with pytest.raises(ValueError, match="otel"):
        Settings.from_env({"GPNARX_OTEL": "jaeger"})


def _run(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_off_imports_nothing_of_opentelemetry():
    # FastAPI itself imports opentelemetry-api (its own dependency): off, gpnarx adds no OpenTelemetry module
    # to those (no SDK, instrumentation or exporter) and leaves the app uninstrumented
    d = _run("""
        import json, sys
        import fastapi
        base = {m for m in sys.modules if m.startswith("opentelemetry")}
        from fastapi.testclient import TestClient
        from gpnarx.service.app import create_app
        from gpnarx.service.settings import Settings
        app = create_app(None, Settings.from_env({}, workers=1))
        with TestClient(app) as c:
            assert c.get("/health/live").status_code == 200
            assert c.get("/v1/models").status_code == 200
        print(json.dumps({"otel": sorted(m for m in sys.modules if m.startswith("opentelemetry") and m not in base),
                          "instrumented": bool(getattr(app, "_is_instrumented_by_opentelemetry", False)),
                          "provider": getattr(app.state, "tracer_provider", None) is not None,
                          "middleware": [m.cls.__name__ for m in app.user_middleware]}))
    """)
    assert d == {"otel": [], "instrumented": False, "provider": False,
                 "middleware": ["GuardMiddleware", "GZipMiddleware"]}


def test_without_the_extra_start_up_fails_naming_it():
    d = _run("""
        import json, sys
        sys.modules["opentelemetry.instrumentation.fastapi"] = None  # the extra's instrumentation not installed
        from gpnarx.service.app import create_app
        from gpnarx.service.settings import Settings
        try:
            create_app(None, Settings(workers=1, otel="console"))
        except ImportError as exc:
            print(json.dumps({"error": str(exc)}))
    """)
    assert "pip install 'gpnarx[otel]'" in d["error"] and "GPNARX_OTEL=console" in d["error"]


def test_gpnarx_serve_reports_the_missing_extra_in_one_line(tmp_path):
    with socket.socket() as s:  # a free port, should the server start after all (the timeout ends it)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = ("import sys; sys.modules['opentelemetry.sdk'] = None; from gpnarx.cli.main import main; "
            f"sys.exit(main(['serve', '--registry', {str(tmp_path)!r}, '--port', '{port}']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "GPNARX_OTEL": "otlp"})
    assert out.returncode != 0
    assert out.stderr.strip().splitlines()[-1].startswith("gpnarx serve: error: GPNARX_OTEL=otlp needs"), out.stderr
    assert "gpnarx[otel]" in out.stderr
