"""X-Request-ID (accepted or generated, echoed, in problems and logs) and the structured log formats."""
from __future__ import annotations

import io
import json
import logging
import logging.config
import re
import sys

import pytest
from fastapi.testclient import TestClient

from gpnarx.service.app import create_app
from gpnarx.service.observability import (
    REQUEST_ID,
    REQUEST_ID_MAX,
    JsonFormatter,
    RequestIdFilter,
    TextFormatter,
    logging_config,
    request_id_for,
)
from gpnarx.service.settings import Settings

GENERATED = re.compile(r"[0-9a-f]{32}")


@pytest.fixture()
def client():
    app = create_app(None, Settings(workers=1, queue_size=0, registry_poll=0))
    log = logging.getLogger("gpnarx.service")

    async def logs_here_and_on_a_worker():
        log.warning("on the event loop")
        await app.state.service.run(lambda: log.warning("on a worker thread"))
        return {"ok": True}

    app.add_api_route("/test-logs", logs_here_and_on_a_worker, methods=["GET"])
    with TestClient(app) as c:
        yield c


def test_a_request_without_an_id_gets_a_generated_one_echoed(client):
    a = client.get("/health/live").headers["x-request-id"]
    b = client.get("/health/live").headers["x-request-id"]
    assert GENERATED.fullmatch(a) and GENERATED.fullmatch(b) and a != b


def test_a_client_id_is_echoed_and_named_in_the_problem(client):
    r = client.get("/v1/models/nope", headers={"X-Request-ID": "plant-7/ch3:0042"})
    assert r.status_code == 404
    assert r.headers["x-request-id"] == "plant-7/ch3:0042"
    assert r.json()["request_id"] == "plant-7/ch3:0042"
    r = client.post("/v1/models/nope/predict", headers={"X-Request-ID": "v-1"}, json={"u": [1.0]})
    assert r.status_code == 422 and r.json()["request_id"] == "v-1" and r.headers["x-request-id"] == "v-1"


@pytest.mark.parametrize("bad", ["has space", "x" * (REQUEST_ID_MAX + 1), "caf\u00e9", "tab\there"])
def test_an_unusable_client_id_is_replaced(client, bad):
    r = client.get("/v1/models/nope", headers={"X-Request-ID": bad.encode("utf-8")})
    rid = r.headers["x-request-id"]
    assert GENERATED.fullmatch(rid) and r.json()["request_id"] == rid


def test_the_longest_id_is_kept():
    assert request_id_for("x" * REQUEST_ID_MAX) == "x" * REQUEST_ID_MAX
    assert request_id_for("") != ""


def test_problems_answered_by_the_middleware_carry_the_id():
    app = create_app(None, Settings(workers=1, queue_size=0, registry_poll=0, api_key="k", max_body_bytes=100))
    with TestClient(app) as c:
        r = c.get("/v1/models", headers={"X-Request-ID": "no-key"})  # 401 from the headers alone
        assert r.status_code == 401 and r.json()["request_id"] == "no-key" and r.headers["x-request-id"] == "no-key"
        r = c.post("/v1/batch", headers={"X-Request-ID": "big", "X-API-Key": "k"}, content=b"x" * 1000)
        assert r.status_code == 413 and r.json()["request_id"] == "big" and r.headers["x-request-id"] == "big"


def test_batch_slot_problems_carry_the_id(client):
    r = client.post("/v1/batch", headers={"X-Request-ID": "b-9"},
                    json={"requests": [{"model": "nope", "u": [1.0], "fs": 1.0}]})
    assert r.status_code == 200 and r.headers["x-request-id"] == "b-9"
    assert r.json()["results"][0]["status"] == 404 and r.json()["results"][0]["request_id"] == "b-9"


def _capture(fmt: str):
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    handler.addFilter(RequestIdFilter())
    return stream, handler


def test_log_lines_of_a_request_carry_its_id_in_json(client):
    stream, handler = _capture("json")
    log = logging.getLogger("gpnarx.service")
    log.addHandler(handler)
    try:
        assert client.get("/test-logs", headers={"X-Request-ID": "log-1"}).status_code == 200
        log.warning("outside")
    finally:
        log.removeHandler(handler)
    lines = [json.loads(s) for s in stream.getvalue().splitlines()]
    assert [(x["message"], x["request_id"]) for x in lines] == [
        ("on the event loop", "log-1"), ("on a worker thread", "log-1"), ("outside", None)]
    for x in lines:
        assert set(x) == {"time", "level", "logger", "message", "request_id"}
        assert x["level"] == "WARNING" and x["logger"] == "gpnarx.service" and x["time"].endswith("Z")


def test_text_lines_name_the_id_inside_a_request_only():
    stream, handler = _capture("text")
    log = logging.getLogger("gpnarx.test_text")
    log.addHandler(handler)
    log.propagate = False
    try:
        token = REQUEST_ID.set("t-1")
        log.warning("inside")
        REQUEST_ID.reset(token)
        log.warning("outside")
    finally:
        log.removeHandler(handler)
    inside, outside = stream.getvalue().splitlines()
    assert inside.endswith("WARNING gpnarx.test_text [t-1] inside")
    assert outside.endswith("WARNING gpnarx.test_text outside")


def test_an_exception_is_one_json_line():
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        rec = logging.getLogger("x").makeRecord("x", logging.ERROR, __file__, 1, "failed", (), sys.exc_info())
    line = JsonFormatter().format(rec)
    assert "\n" not in line and "RuntimeError: boom" in json.loads(line)["exc_info"]


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_logging_config_is_a_valid_dict_config(fmt):
    cfg = logging_config(fmt, "warning")
    logging.config.dictConfig(cfg)  # raises on a malformed config
    try:
        handler = logging.getLogger("gpnarx").handlers[0]
        assert isinstance(handler.formatter, JsonFormatter if fmt == "json" else TextFormatter)
        assert logging.getLogger("uvicorn.access").handlers[0] is handler
    finally:
        for name in ("gpnarx", "uvicorn", "uvicorn.access"):
            lg = logging.getLogger(name)
            lg.handlers.clear()
            lg.propagate = True
            lg.setLevel(logging.NOTSET)


def test_log_format_setting():
    assert Settings().log_format == "text"
    assert Settings.from_env({"GPNARX_LOG_FORMAT": "json"}).log_format == "json"
    with pytest.raises(ValueError, match="log_format"):
        Settings.from_env({"GPNARX_LOG_FORMAT": "xml"})
    with pytest.raises(ValueError):
        logging_config("xml")
