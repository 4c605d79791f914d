"""Every route's JSON answer against the committed OpenAPI document (openapi/openapi.json).

Each answer is validated with ``jsonschema`` against the schema the document gives for its route, status
and media type, with every object schema closed (``additionalProperties: false`` unless the document
says otherwise), so an answer member the document does not describe fails too. The routes validate
their answers by their response models at run time (``service.answers``); this checks the document
the clients are generated from.
"""
from __future__ import annotations

import copy
import io
import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from jsonschema import Draft202012Validator
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012
from test_service_support import FS, built_registry, short_record

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOC = json.loads((ROOT / "openapi" / "openapi.json").read_text())


def _closed(schema):
    """``schema`` with each object schema that lists properties closed to other members."""
    if isinstance(schema, dict):
        out = {k: _closed(v) for k, v in schema.items()}
        if "properties" in out and "additionalProperties" not in out:
            out["additionalProperties"] = False
        return out
    if isinstance(schema, list):
        return [_closed(v) for v in schema]
    return schema


CLOSED = _closed(copy.deepcopy(DOC))
REGISTRY = Registry().with_resource("urn:openapi", Resource(contents=CLOSED, specification=DRAFT202012))


def check(r, path: str, method: str = "post"):
    """Validate response ``r`` of ``method path`` (the document's path template) against its schema."""
    media = r.headers["content-type"].split(";")[0]
    op = DOC["paths"][path][method]
    content = op["responses"][str(r.status_code)]["content"]
    assert media in content, (path, r.status_code, media, list(content))
    pointer = ["paths", path, method, "responses", str(r.status_code), "content", media, "schema"]
    schema = {"$ref": "urn:openapi#/" + "/".join(p.replace("~", "~0").replace("/", "~1") for p in pointer)}
    errors = sorted(Draft202012Validator(schema, registry=REGISTRY).iter_errors(r.json()), key=lambda e: e.path)
    assert not errors, f"{method.upper()} {path} {r.status_code}: " + "; ".join(
        f"{'/'.join(map(str, e.absolute_path))}: {e.message}"[:300] for e in errors[:5])
    return r.json()


@pytest.fixture(scope="module")
def client():
    app = create_app(built_registry().root, Settings.from_env({}, workers=2, queue_size=8, registry_poll=0.0))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def record(n=96, seed=5, y=True, **extra):
    u, yy = short_record(n, seed)
    body = {"u": u.tolist(), "fs": FS, "mc_paths": 16, "seed": 0, **extra}
    if y:
        body["y"] = yy.tolist()
    return body


OPS = [("predict", {}), ("predict", {"y": False, "method": "linear"}), ("predict", {"return_state": True}),
       ("loops", {"n": 400}), ("loops", {"n": 400, "method": "linear", "y": False}), ("novelty", {"n": 256}),
       ("novelty", {"n": 256, "method": "linear", "start": "rest"}),
       ("loops", {"n": 400, "method": "linear", "return_state": True}),  # stream: basis 'stream'
       ("novelty", {"n": 256, "method": "linear", "return_state": True})]  # stream: novelty_window


@pytest.mark.parametrize("op, kw", OPS)
def test_operation_answers_match_the_document(client, op, kw):
    kw = dict(kw)
    body = record(kw.pop("n", 96), y=kw.pop("y", True), **kw)
    r = client.post(f"/v1/models/boucwen/{op}", json=body)
    assert r.status_code == 200, r.text
    check(r, f"/v1/models/{{name}}/{op}")
    r = client.post(f"/v1/models/boucwen/versions/1/{op}", json=body)
    assert r.status_code == 200, r.text
    check(r, f"/v1/models/{{name}}/versions/{{version}}/{op}")


def test_stream_continuation_matches_the_document(client):
    first = client.post("/v1/models/boucwen/predict", json=record(return_state=True)).json()
    r = client.post("/v1/models/boucwen/predict", json=record(seed=6, state=first["state"]))
    assert r.status_code == 200, r.text
    assert check(r, "/v1/models/{name}/predict")["start"] == "state"


def test_batch_answer_matches_the_document(client):
    items = [{"model": "boucwen", "operation": op, **record(n)} for op, n in (("predict", 96), ("loops", 400),
                                                                              ("novelty", 256))]
    items += [{"model": "plain", "operation": "loops", **record()},  # a problem in its slot (409)
              {"model": "boucwen", "u": "nope", "fs": FS}]  # a validation problem in its slot (422)
    r = client.post("/v1/batch", json={"requests": items})
    assert r.status_code == 200, r.text
    results = check(r, "/v1/batch")["results"]
    assert [x.get("status") for x in results[3:]] == [409, 422]


def test_metadata_and_health_answers_match_the_document(client):
    check(client.get("/v1/models"), "/v1/models", "get")
    check(client.get("/v1/models/boucwen"), "/v1/models/{name}", "get")
    check(client.get("/v1/models/plain"), "/v1/models/{name}", "get")
    check(client.get("/v1/models/boucwen/versions/2"), "/v1/models/{name}/versions/{version}", "get")
    check(client.get("/health/live"), "/health/live", "get")
    check(client.get("/health/ready"), "/health/ready", "get")
    check(client.post("/v1/admin/reload"), "/v1/admin/reload")


def test_parsed_record_matches_the_document(client):
    u, y = short_record(64)
    buf = io.BytesIO()
    np.savez(buf, u=u, y=y, fs=FS)
    r = client.post("/v1/records/parse", files={"files": ("r.npz", buf.getvalue(), "application/octet-stream")})
    assert r.status_code == 200, r.text
    check(r, "/v1/records/parse")


@pytest.mark.parametrize("method, path, template, kw, status", [
    ("post", "/v1/models/boucwen/predict", "/v1/models/{name}/predict", {"json": {"u": [1.0], "fs": 1.0}}, 422),
    ("post", "/v1/models/boucwen/predict", "/v1/models/{name}/predict", {"json": {"u": "x"}}, 422),
    ("post", "/v1/models/boucwen/predict", "/v1/models/{name}/predict", {"content": b"{", "headers": {
        "content-type": "application/json"}}, 400),
    ("post", "/v1/models/nosuch/predict", "/v1/models/{name}/predict", {"json": {"u": [1.0], "fs": FS}}, 404),
    ("post", "/v1/models/plain/loops", "/v1/models/{name}/loops", {"json": {"u": [1.0] * 32, "fs": FS}}, 409),
    ("post", "/v1/models/plain/novelty", "/v1/models/{name}/novelty",
     {"json": {"u": [1.0] * 32, "y": [0.0] * 32, "fs": FS}}, 409),
    ("post", "/v1/models/boucwen/predict", "/v1/models/{name}/predict",
     {"json": {"u": [1.0] * 5000, "fs": FS, "mc_paths": 4096}}, 413),
    ("post", "/v1/batch", "/v1/batch", {"json": {"requests": []}}, 422),
    ("post", "/v1/batch", "/v1/batch", {"content": b"x", "headers": {"content-type": "text/plain"}}, 415),
    ("get", "/v1/models/nosuch", "/v1/models/{name}", {}, 404),
    ("get", "/v1/models/boucwen/versions/9", "/v1/models/{name}/versions/{version}", {}, 404),
])
def test_problem_answers_match_the_document(client, method, path, template, kw, status):
    r = client.request(method.upper(), path, **kw)
    assert r.status_code == status, r.text
    check(r, template, method)


def test_an_answer_off_its_model_is_a_500_not_sent(client, monkeypatch):
    from gpnarx.service.routers import models

    monkeypatch.setattr(models, "summary_of", lambda reg, n: {"name": n})  # lacks the required members
    r = client.get("/v1/models")
    assert r.status_code == 500 and "does not match its documented schema" in r.json()["detail"]
    check(r, "/v1/models", "get")
