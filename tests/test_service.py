"""HTTP service tests: through a real uvicorn server on 127.0.0.1 and through TestClient.

The registry (``test_service_support.built_registry``) holds a small Bouc-Wen GP-NARX as
``boucwen`` versions 1 and 2 (physics and novelty calibration) and ``plain`` 1 (neither).
"""
from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import (
    FS,
    MC_PATHS,
    LiveServer,
    built_registry,
    copy_registry,
    multisine,
    noisy,
    short_record,
    simulate,
)

from gpnarx.service.app import create_app, openapi_json
from gpnarx.service.settings import DEFAULT_BOUNDS, Settings

ROOT = Path(__file__).resolve().parents[1]
PROBLEM = "application/problem+json"


def settings(**kw):
    base = dict(workers=2, queue_size=8)
    base.update(kw)
    return Settings(**base)


@pytest.fixture(scope="module")
def registry():
    return built_registry().root


@pytest.fixture(scope="module")
def client(registry):
    return TestClient(create_app(registry, settings()), raise_server_exceptions=False)


@pytest.fixture(scope="module")
def live(registry):
    with LiveServer(create_app(registry, settings())) as srv:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            yield c


def rec(n=96, seed=5, **extra):
    u, y = short_record(n, seed)
    body = {"u": u.tolist(), "fs": FS, "mc_paths": 32, "seed": 0}
    body.update(extra)
    return body, y


def assert_problem(r, status, field=None):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM), r.headers["content-type"]
    p = r.json()
    assert p["status"] == status and p["title"] and p["type"] and p["detail"]
    assert "Traceback" not in r.text and 'File "' not in r.text
    if field is not None:
        assert p["field"] == field, p
    return p


# ------------------------------------------------------------------------------------------ OpenAPI
def test_committed_openapi_matches_app():
    committed = (ROOT / "openapi" / "openapi.json").read_text()
    assert committed == openapi_json(), "openapi/openapi.json drifted: run `gpnarx export-openapi`"
    doc = json.loads(committed)
    paths = doc["paths"]
    for p in ("/v1/models", "/v1/models/{name}", "/v1/models/{name}/predict", "/v1/models/{name}/loops",
              "/v1/models/{name}/novelty", "/v1/models/{name}/versions/{version}/predict",
              "/v1/models/{name}/versions/{version}/loops", "/v1/models/{name}/versions/{version}/novelty",
              "/v1/batch", "/health/live", "/health/ready", "/metrics", "/v1/admin/reload"):
        assert p in paths, p
    req = doc["components"]["schemas"]["RecordRequest"]["properties"]
    assert set(req) >= {"u", "fs", "y", "y0", "mc_paths", "seed", "confidence"}
    assert str(DEFAULT_BOUNDS["mc_paths_max"]) in req["mc_paths"]["description"]
    assert str(DEFAULT_BOUNDS["max_samples"]) in req["u"]["description"]
    assert PROBLEM in paths["/v1/models/{name}/predict"]["post"]["responses"]["422"]["content"]


def test_cli_export_openapi(tmp_path):
    from gpnarx.cli.main import main

    out = tmp_path / "doc.json"
    assert main(["export-openapi", "--out", str(out)]) == 0
    assert out.read_text() == (ROOT / "openapi" / "openapi.json").read_text()


def test_cli_serve_without_builder_is_one_line_error(monkeypatch, capsys):
    from gpnarx.cli.main import main

    monkeypatch.setitem(sys.modules, "gpnarx.training.defaults", None)  # import fails
    assert main(["serve"]) == 1  # a runtime error: the command line is fine
    err = capsys.readouterr().err
    assert "default registry builder is not available" in err and err.count("\n") == 1


# ------------------------------------------------------------------------------------------ health, models
def test_health_models_and_metrics(client):
    assert client.get("/health/live").json() == {"status": "alive"}
    r = client.get("/health/ready")
    assert r.status_code == 200
    assert r.json()["models"] == {"boucwen": ["1", "2"], "plain": ["1"]} and r.json()["refused"] == []
    models = {m["name"]: m for m in client.get("/v1/models").json()["models"]}
    assert models["boucwen"]["latest"] == "2" and models["boucwen"]["novelty"] is True
    assert models["plain"]["novelty"] is False
    d = client.get("/v1/models/boucwen").json()
    assert d["version"] == "2" and d["versions"] == ["1", "2"] and d["fs"] == FS
    assert d["lags"] == {"ny": 10, "nu": 10} and d["units"] == {"u": "N", "y": "m"}
    assert {"kernel", "hyperparameters", "training", "novelty", "physics"} <= set(d)
    assert d["noise_calibration"] is None  # trained with ML-II's noise variance
    assert d["novelty"]["false_alarm_rate"] == 0.01 and d["physics"]["mass"] == 2.0
    assert client.get("/v1/models/boucwen/versions/1").json()["version"] == "1"
    assert_problem(client.get("/v1/models/nope"), 404, "name")
    assert_problem(client.get("/v1/models/boucwen/versions/7"), 404, "version")
    text = client.get("/metrics").text
    for name in ("gpnarx_http_requests_total", "gpnarx_http_errors_total", "gpnarx_http_request_duration_seconds",
                 "gpnarx_mc_path_steps_total", "gpnarx_bundles_loaded 3.0", "gpnarx_bundles_refused 0.0"):
        assert name in text, name
    assert 'route="/v1/models/{name}"' in text


def test_empty_registry_not_ready(tmp_path):
    c = TestClient(create_app(tmp_path, settings()), raise_server_exceptions=False)
    p = assert_problem(c.get("/health/ready"), 503)
    assert p["refused"] == [] and p["bundles"] == 0
    assert c.get("/health/live").status_code == 200


# ------------------------------------------------------------------------------------------ predict
def test_predict_band_covers_boucwen_multisine_live(live):
    """Real server: 99% band on an unseen 10 N RMS Bouc-Wen multisine covers >= 95% of the samples."""
    b = built_registry()
    body = {"u": b.test_u.tolist(), "fs": FS, "y": b.test_y.tolist(), "mc_paths": 128, "seed": 0}
    r = live.post("/v1/models/boucwen/predict", json=body)
    assert r.status_code == 200, r.text
    d = r.json()
    n = b.test_u.size
    assert d["model"] == "boucwen" and d["version"] == "2" and d["confidence"] == 0.99
    assert d["mc_paths"] == 128 and d["method"] == "mc"
    for k in ("mean", "lower", "upper", "std"):
        assert len(d[k]) == n
    assert np.all(np.asarray(d["lower"]) <= np.asarray(d["upper"]))
    assert d["coverage"] >= 95.0, d["coverage"]
    assert d["fit"] > 60.0 and d["rmse"] > 0
    y, lo, hi = b.test_y, np.asarray(d["lower"]), np.asarray(d["upper"])
    assert abs(100 * np.mean((y >= lo) & (y <= hi)) - d["coverage"]) < 1e-9


def test_predict_without_y_and_linear(client):
    body, _ = rec()
    d = client.post("/v1/models/boucwen/predict", json=body).json()
    assert not {"fit", "rmse", "coverage"} & set(d)
    d = client.post("/v1/models/boucwen/predict", json={**body, "method": "linear"}).json()
    assert d["method"] == "linear" and d["mc_paths"] == 0 and len(d["mean"]) == 96
    body["y0"] = [0.0] * 10
    d = client.post("/v1/models/boucwen/predict", json=body).json()
    assert d["mean"][:10] == [0.0] * 10 and d["std"][:10] == [0.0] * 10
    # default mc_paths
    body.pop("mc_paths")
    body["u"] = body["u"][:20]
    body.pop("y0")
    assert client.post("/v1/models/boucwen/predict", json=body).json()["mc_paths"] == MC_PATHS  # the model's


def test_determinism_across_runs_and_worker_counts(registry, client):
    body, y = rec(n=80, seed=9, y=None)
    body["y"] = y.tolist()
    first = client.post("/v1/models/boucwen/versions/1/predict", json=body)
    again = client.post("/v1/models/boucwen/versions/1/predict", json=body)
    assert first.status_code == 200 and first.content == again.content
    other = TestClient(create_app(registry, Settings(workers=1, queue_size=2)))
    assert other.post("/v1/models/boucwen/versions/1/predict", json=body).content == first.content
    changed = client.post("/v1/models/boucwen/versions/1/predict", json={**body, "seed": 1})
    assert changed.json()["mean"] != first.json()["mean"]


def test_version_routes(client):
    body, y = rec(n=40)
    for op in ("predict", "loops"):
        r = client.post(f"/v1/models/boucwen/versions/1/{op}", json=body)
        assert r.status_code == 200 and r.json()["version"] == "1"
    r = client.post("/v1/models/boucwen/versions/1/novelty", json={**body, "y": y.tolist()})
    assert r.status_code == 200 and r.json()["version"] == "1"
    assert_problem(client.post("/v1/models/boucwen/versions/5/predict", json=body), 404, "version")


# ------------------------------------------------------------------------------------------ loops, novelty
def test_loops(client):
    body, y = rec(n=128)
    d = client.post("/v1/models/boucwen/loops", json={**body, "y": y.tolist()}).json()
    assert d["physics"]["mass"] == 2.0 and d["physics"]["output"] == "displacement"
    assert d["units"] == {"x": "m", "force": "N", "energy": "J", "stiffness": "N/m"}
    for k in ("predicted", "lower", "upper", "measured"):
        assert len(d[k]["x"]) == len(d[k]["force"]) == 128 and d[k]["area"] >= 0
    # R = u - m x'' for a displacement output: the predicted loop's x is the predicted mean
    pred = client.post("/v1/models/boucwen/predict", json=body).json()
    assert np.allclose(d["predicted"]["x"], pred["mean"])
    assert "measured" not in client.post("/v1/models/boucwen/loops", json=body).json()
    assert_problem(client.post("/v1/models/plain/loops", json=body), 409)


def test_novelty_healthy_and_damaged(client):
    from gpnarx.training.simulators.boucwen import BoucWen

    u = multisine(384, 21)
    base = {"u": u.tolist(), "fs": FS, "mc_paths": 64, "seed": 0}
    healthy = client.post("/v1/models/boucwen/novelty", json={**base, "y": noisy(simulate(u), 21).tolist()}).json()
    assert healthy["verdict"] == "healthy", healthy
    assert healthy["false_alarm_rate"] == 0.01 and healthy["threshold"] > 0 and "nlpd" in healthy
    assert healthy["score_method"] == "rms_standardised_residual"  # a bundle calibrated without a method
    y_dmg = noisy(BoucWen(k=3.0e4).simulate(u)["y"], 21)  # stiffness loss: a loosened joint
    damaged = client.post("/v1/models/boucwen/novelty", json={**base, "y": y_dmg.tolist()}).json()
    assert damaged["verdict"] == "novel" and damaged["score"] > damaged["threshold"]
    assert_problem(client.post("/v1/models/boucwen/novelty", json=base), 422, "y")
    p = assert_problem(client.post("/v1/models/plain/novelty", json={**base, "y": u.tolist()}), 409, "name")
    assert "gpnarx calibrate" in p["detail"] and "bert-real-monitor" in p["detail"]


def test_novelty_outside_the_calibration_envelope_is_novel(client):
    u = multisine(384, 23)
    y = noisy(simulate(u), 23)
    base = {"u": u.tolist(), "fs": FS, "mc_paths": 32, "seed": 0}
    inside = client.post("/v1/models/boucwen/novelty", json={**base, "y": y.tolist()}).json()
    assert inside["out_of_range"] == [] and inside["verdict"] == "healthy", inside
    huge = client.post("/v1/models/boucwen/novelty", json={**base, "y": (1e6 * y).tolist()}).json()
    assert huge["out_of_range"] == ["y", "prediction"] and huge["verdict"] == "novel", huge
    assert huge["diverged_paths"] == 32, huge  # started from the huge measured outputs: every path outside
    # a probe at 1/10 of the calibrated amplitude, answered by the system: the model was not calibrated there
    small = client.post("/v1/models/boucwen/novelty", json={**base, "u": (0.1 * u).tolist(),
                                                             "y": noisy(simulate(0.1 * u), 23).tolist()}).json()
    assert set(small["out_of_range"]) == {"u", "y"} and small["verdict"] == "novel", small
    # version 1 was calibrated without an envelope: no range check, the score alone decides
    body = {**base, "u": (0.1 * u).tolist(), "y": noisy(simulate(0.1 * u), 23).tolist()}
    old = client.post("/v1/models/boucwen/versions/1/novelty", json=body).json()
    assert old["out_of_range"] == [] and old["verdict"] == ("novel" if old["score"] > old["threshold"] else "healthy")


def test_novelty_starts_from_the_measured_record_unless_y0_is_given(client):
    u = multisine(384, 22)
    y = noisy(simulate(u), 22)
    base = {"u": u.tolist(), "fs": FS, "mc_paths": 32, "seed": 0, "y": y.tolist()}
    default = client.post("/v1/models/boucwen/novelty", json=base).json()
    ny = client.get("/v1/models/boucwen").json()["lags"]["ny"]
    measured = client.post("/v1/models/boucwen/novelty", json={**base, "y0": y[:ny].tolist()}).json()
    assert default["score"] == measured["score"]  # the rule of model.novelty.novelty_start
    y0_rest = [0.0] * ny
    from_rest = client.post("/v1/models/boucwen/novelty", json={**base, "y0": y0_rest}).json()
    assert from_rest["score"] != default["score"]  # an explicit y0 still wins


# ------------------------------------------------------------------------------------------ batch
def test_batch_live_one_malformed_record(live):
    body, y = rec(n=64)
    items = [
        {"model": "boucwen", **body},
        {"model": "boucwen", **body, "mc_paths": "many"},  # malformed
        {"model": "boucwen", "version": "1", "operation": "novelty", **body, "y": y.tolist()},
        {"model": "boucwen", "operation": "loops", **body},
    ]
    r = live.post("/v1/batch", json={"requests": items})
    assert r.status_code == 200, r.text
    res = r.json()["results"]
    assert len(res) == 4
    assert len(res[0]["mean"]) == 64 and res[0]["version"] == "2"
    assert res[1]["status"] == 422 and res[1]["field"] == "requests.1.mc_paths" and res[1]["detail"]
    assert res[2]["verdict"] in ("healthy", "novel") and res[2]["version"] == "1"
    assert "predicted" in res[3]
    # the batch answer equals the single call's
    single = live.post("/v1/models/boucwen/predict", json=body).json()
    assert single["mean"] == res[0]["mean"]


def test_batch_each_item_fails_on_its_own(client):
    body, y = rec(n=32)
    items = [
        7,
        {"model": "nope", **body},
        {"model": "../etc", **body},
        {"model": "boucwen", **body, "fs": 1000.0},
        {"model": "plain", "operation": "novelty", **body, "y": y.tolist()},
        {"model": "boucwen", "operation": "novelty", **body},
        {"model": "boucwen", **body, "u": [1.0, "x"]},  # (a null is a gap, model.gaps)
        {"model": "boucwen", **body, "extra": 1},
        {"model": "boucwen", **body},
    ]
    res = client.post("/v1/batch", json={"requests": items}).json()["results"]
    fields = [r.get("field") for r in res[:-1]]
    assert [r["status"] for r in res[:-1]] == [422, 404, 422, 422, 409, 422, 422, 422]
    assert fields[0] == "requests.0" and fields[1] == "requests.1.model" and fields[2] == "requests.2.model"
    assert fields[3] == "requests.3.fs" and fields[5] == "requests.5.y" and fields[6] == "requests.6.u.1"
    assert fields[7] == "requests.7.extra"
    assert "1000" in res[3]["detail"] and "750" in res[3]["detail"]
    assert len(res[-1]["mean"]) == 32


def test_batch_envelope_errors(client):
    assert_problem(client.post("/v1/batch", json={"requests": []}), 422, "requests")
    assert_problem(client.post("/v1/batch", json={"requests": {}}), 422, "requests")
    assert_problem(client.post("/v1/batch", json=[1]), 422, "body")
    assert_problem(client.post("/v1/batch", json={"requests": [], "x": 1}), 422, "x")
    assert_problem(client.post("/v1/batch", content=b"{not json", headers={"content-type": "application/json"}),
                   400, "body")
    assert_problem(client.post("/v1/batch", content=b"x", headers={"content-type": "text/plain"}), 415, "body")


# ------------------------------------------------------------------------------------------ bounds and bad input
def test_bounds(registry):
    c = TestClient(create_app(registry, settings(max_samples=100, max_batch=2, mc_paths_default=16, mc_paths_max=64,
                                                 max_mc_work=2000, max_body_bytes=20000)),
                   raise_server_exceptions=False)
    body, _ = rec(n=50)
    p = assert_problem(c.post("/v1/models/boucwen/predict", json={**body, "u": [0.0] * 101}), 413, "u")
    assert "100" in p["detail"] and p["limit"] == 100
    p = assert_problem(c.post("/v1/models/boucwen/predict", json={**body, "mc_paths": 65}), 422, "mc_paths")
    assert "64" in p["detail"]
    p = assert_problem(c.post("/v1/models/boucwen/predict", json={**body, "mc_paths": 41}), 413, "mc_paths")
    assert "2000" in p["detail"]
    assert c.post("/v1/models/boucwen/predict", json={**body, "mc_paths": 40}).status_code == 200
    p = assert_problem(c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}] * 3}), 413, "requests")
    assert "2" in p["detail"]
    # a batch shares one Monte Carlo budget: the second record does not fit any more
    res = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body, "mc_paths": 30}] * 2}).json()["results"]
    assert "mean" in res[0] and res[1]["status"] == 413 and res[1]["field"] == "requests.1.mc_paths"
    p = assert_problem(c.post("/v1/models/boucwen/predict", json={**body, "u": [0.5] * 5000}), 413, "body")
    assert "20000" in p["detail"]


@pytest.mark.parametrize("payload, status, field", [
    ({"u": [], "fs": FS}, 422, "u"),
    ({"u": [1.0, "2"], "fs": FS}, 422, "u.1"),
    ({"u": [True], "fs": FS}, 422, "u.0"),
    ({"u": "1,2,3", "fs": FS}, 422, "u"),
    ({"fs": FS}, 422, "u"),
    ({"u": [1.0]}, 422, "fs"),
    ({"u": [1.0], "fs": 0}, 422, "fs"),
    ({"u": [1.0], "fs": 749.0}, 422, "fs"),
    ({"u": [1.0], "fs": FS, "mc_paths": 0}, 422, "mc_paths"),
    ({"u": [1.0], "fs": FS, "mc_paths": -3}, 422, "mc_paths"),
    ({"u": [1.0], "fs": FS, "mc_paths": 2.5}, 422, "mc_paths"),
    ({"u": [1.0], "fs": FS, "mc_paths": 10**6}, 422, "mc_paths"),
    ({"u": [1.0], "fs": FS, "seed": -1}, 422, "seed"),
    ({"u": [1.0], "fs": FS, "confidence": 1.0}, 422, "confidence"),
    ({"u": [1.0], "fs": FS, "method": "exact"}, 422, "method"),
    ({"u": [1.0, 2.0], "fs": FS, "y": [1.0]}, 422, "y"),
    ({"u": [1.0] * 20, "fs": FS, "y0": [0.0, 0.0]}, 422, "y0"),
    ({"u": [1.0] * 5, "fs": FS, "y0": [0.0] * 10}, 422, "u"),
    ({"u": [1.0], "fs": FS, "bogus": 1}, 422, "bogus"),
    ([1, 2], 422, "body"),
])
def test_bad_inputs_are_problems(client, payload, status, field):
    assert_problem(client.post("/v1/models/boucwen/predict", json=payload), status, field)


@pytest.mark.parametrize("raw", [b'{"u": [NaN], "fs": 750}', b'{"u": [Infinity], "fs": 750}',
                                 b'{"u": [1e400], "fs": 750}'])
def test_non_finite_numbers_refused(client, raw):
    p = assert_problem(client.post("/v1/models/boucwen/predict", content=raw,
                                   headers={"content-type": "application/json"}), 422, "u.0")
    assert "finite" in p["detail"]


def test_hostile_bodies_and_paths(client):
    for raw in (b"", b"{", b"[" * 100000 + b"]" * 100000, b"\xff\xfe", b"null"):
        r = client.post("/v1/models/boucwen/predict", content=raw, headers={"content-type": "application/json"})
        assert 400 <= r.status_code < 500, (raw[:10], r.status_code)
        assert_problem(r, r.status_code)
    deep = b'{"requests": ' + b"[" * 50000 + b"]" * 50000 + b"}"
    r = client.post("/v1/batch", content=deep, headers={"content-type": "application/json"})
    if r.status_code == 200:  # parsed (orjson): the one record is refused on its own
        assert r.json()["results"][0]["status"] == 422 and r.json()["results"][0]["field"] == "requests.0"
    else:  # refused by the JSON parser
        assert_problem(r, 400, "body")
    body, _ = rec(n=8)
    for path in ("/v1/models/..%2F..%2Fetc%2Fpasswd/predict", "/v1/models/%2e%2e/predict", "/v1/models/a..b/predict",
                 "/v1/models/-x/predict", "/v1/models/boucwen/versions/..%2F1/predict",
                 "/v1/models/boucwen/versions/0/predict", "/v1/models/boucwen/versions/1a/loops",
                 "/v1/models/" + "a" * 65 + "/predict"):
        r = client.post(path, json=body)
        assert r.status_code in (404, 422), (path, r.status_code)
        assert_problem(r, r.status_code)
    assert_problem(client.get("/v1/nothing"), 404)
    assert_problem(client.delete("/v1/models"), 405)


def test_unexpected_error_is_a_500_problem(registry, monkeypatch):
    from gpnarx.service import ops

    def boom(*a, **k):
        raise RuntimeError("secret internals /etc/passwd")

    c = TestClient(create_app(registry, settings()), raise_server_exceptions=False)
    monkeypatch.setattr(ops, "compute", boom)
    body, _ = rec(n=8)
    p = assert_problem(c.post("/v1/models/boucwen/predict", json=body), 500)
    assert "secret" not in json.dumps(p) and "incident" in p
    res = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}]}).json()["results"]
    assert res[0]["status"] == 500 and "secret" not in json.dumps(res)


# ------------------------------------------------------------------------------------------ auth
def test_api_key(registry):
    with LiveServer(create_app(registry, settings(api_key="s3cret"))) as srv:
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            body, _ = rec(n=8)
            p = assert_problem(c.post("/v1/models/boucwen/predict", json=body), 401, "X-API-Key")
            assert "WWW-Authenticate" in c.get("/v1/models").headers
            assert_problem(c.get("/v1/models", headers={"X-API-Key": "wrong"}), 401)
            assert_problem(c.post("/v1/batch", content=b"{bad", headers={"X-API-Key": "s3cret!"}), 401)
            assert_problem(c.post("/v1/admin/reload"), 401)
            assert c.get("/v1/models", headers={"X-API-Key": "s3cret"}).status_code == 200
            r = c.post("/v1/models/boucwen/predict", json=body, headers={"X-API-Key": "s3cret"})
            assert r.status_code == 200
            for open_path in ("/health/live", "/health/ready", "/metrics"):
                assert c.get(open_path).status_code == 200
            assert "secret" not in p["detail"]
            # answered before routing, yet counted under the route it was for (not "unmatched")
            text = c.get("/metrics").text
            assert 'gpnarx_http_requests_total{method="POST",route="/v1/models/{name}/predict",status="401"}' in text
            assert 'route="unmatched",status="401"' not in text


def test_openapi_declares_the_key_scheme_only_when_a_key_is_set(registry):
    """Without GPNARX_API_KEY the document has no security scheme (Swagger UI shows no lock on any route); with
    one, every /v1 operation requires ApiKeyAuth (the X-API-Key header) and /health/* stay open."""
    def ops(doc):
        return {(path, m): op for path, item in doc["paths"].items() for m, op in item.items()}

    plain = create_app(registry, settings()).openapi()
    assert "securitySchemes" not in plain["components"] and not any("security" in op for op in ops(plain).values())
    committed = json.loads((ROOT / "openapi" / "openapi.json").read_text())
    assert "securitySchemes" not in committed["components"]
    keyed = create_app(registry, settings(api_key="s3cret")).openapi()
    assert keyed["components"]["securitySchemes"]["ApiKeyAuth"] == {
        "type": "apiKey", "in": "header", "name": "X-API-Key",
        "description": "Required on /v1 routes only when the server sets GPNARX_API_KEY."}
    for (path, _), op in ops(keyed).items():
        assert op.get("security") == ([{"ApiKeyAuth": []}] if path.startswith("/v1/") else None), path
    with TestClient(create_app(registry, settings())) as c:  # the served document and Swagger UI follow it
        assert "securitySchemes" not in c.get("/openapi.json").json()["components"]


# ------------------------------------------------------------------------------------------ load shedding, liveness
def _wait(cond, timeout=20.0):
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError("condition not reached")
        time.sleep(0.01)


def test_queue_full_sheds_503_and_live_stays_fast(registry):
    app = create_app(registry, settings(workers=1, queue_size=0, retry_after=3))
    executor = app.state.service.executor
    u = multisine(2000, 31)
    long_body = {"u": u.tolist(), "fs": FS, "mc_paths": 128, "seed": 0}
    with LiveServer(app) as srv:
        out = {}

        def long_call():
            with httpx.Client(base_url=srv.url, timeout=120) as c:
                out["r"] = c.post("/v1/models/boucwen/predict", json=long_body)

        t = threading.Thread(target=long_call)
        t.start()
        try:
            _wait(lambda: executor.pending >= 1)
            with httpx.Client(base_url=srv.url, timeout=30) as c:
                body, _ = rec(n=8)
                p = assert_problem(c.post("/v1/models/boucwen/predict", json=body), 503)
                r = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}]})
                assert r.status_code == 503 and r.headers["Retry-After"] == "3"
                lat = []
                for _ in range(10):
                    t0 = time.perf_counter()
                    assert c.get("/health/live").status_code == 200
                    lat.append(time.perf_counter() - t0)
                assert executor.pending >= 1, "the long prediction finished too early to test liveness"
                assert np.median(lat) < 0.2, lat
                assert "busy" in p["detail"]
                assert "gpnarx_requests_shed_total 2.0" in c.get("/metrics").text
        finally:
            t.join(timeout=120)
        assert out["r"].status_code == 200 and len(out["r"].json()["mean"]) == 2000


# ------------------------------------------------------------------------------------------ faults, reload
def test_corrupted_bundle_refused_others_serve_and_reload(tmp_path):
    from gpnarx.storage.bundle import save_bundle

    root = copy_registry(tmp_path / "reg")
    npy = sorted((root / "boucwen" / "2").glob("*.npy"))[0]
    raw = bytearray(npy.read_bytes())
    raw[-3] ^= 0xFF  # flip a byte in the data
    npy.write_bytes(bytes(raw))
    app = create_app(root, settings())
    body, _ = rec(n=48)
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        ready = c.get("/health/ready")
        assert ready.status_code == 200
        refused = ready.json()["refused"]
        assert [r["path"] for r in refused] == ["boucwen/2"]
        assert "checksum" in refused[0]["reason"] and str(tmp_path) not in refused[0]["reason"]
        assert ready.json()["models"] == {"boucwen": ["1"], "plain": ["1"]}
        r = c.post("/v1/models/boucwen/predict", json=body)
        assert r.status_code == 200 and r.json()["version"] == "1"
        assert c.post("/v1/models/plain/predict", json=body).status_code == 200
        assert_problem(c.post("/v1/models/boucwen/versions/2/predict", json=body), 404, "version")
        assert "gpnarx_bundles_refused 1.0" in c.get("/metrics").text

        # reload while a prediction is in flight: it completes; new and removed bundles are picked up
        u = multisine(1500, 41)
        out = {}

        def long_call():
            with httpx.Client(base_url=srv.url, timeout=120) as c2:
                out["r"] = c2.post("/v1/models/plain/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": 128})

        t = threading.Thread(target=long_call)
        t.start()
        _wait(lambda: app.state.service.executor.pending >= 1)
        save_bundle(built_registry().model, root, "boucwen", "3", fs=FS, units={"u": "N", "y": "m"},
                    physics={"mass": 2.0}, novelty=None, training={})
        import shutil

        shutil.rmtree(root / "plain")
        rr = c.post("/v1/admin/reload")
        assert rr.status_code == 200, rr.text
        d = rr.json()
        assert d["added"] == ["boucwen:3"] and d["removed"] == ["plain:1"]
        assert [r["path"] for r in d["refused"]] == ["boucwen/2"]
        t.join(timeout=120)
        assert out["r"].status_code == 200 and len(out["r"].json()["mean"]) == 1500
        assert c.post("/v1/models/boucwen/predict", json=body).json()["version"] == "3"
        assert_problem(c.post("/v1/models/plain/predict", json=body), 404, "name")


def test_reload_without_registry_is_409():
    c = TestClient(create_app(None, settings()), raise_server_exceptions=False)
    assert_problem(c.post("/v1/admin/reload"), 409)


# ------------------------------------------------------------------------------------------ body cap on the wire
def test_body_cap_streamed_and_declared(registry):
    with LiveServer(create_app(registry, settings(max_body_bytes=4096))) as srv:
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            big = json.dumps({"u": [0.123456789] * 2000, "fs": FS}).encode()
            assert_problem(c.post("/v1/models/boucwen/predict", content=big,
                                  headers={"content-type": "application/json"}), 413, "body")

            def chunks():  # no Content-Length: chunked transfer, counted while reading
                for i in range(0, len(big), 1000):
                    yield big[i:i + 1000]

            r = c.post("/v1/models/boucwen/predict", content=chunks(), headers={"content-type": "application/json"})
            assert "content-length" not in {k.lower() for k in r.request.headers}
            assert_problem(r, 413, "body")
            r = c.post("/v1/batch", content=chunks(), headers={"content-type": "application/json"})
            assert_problem(r, 413, "body")
            assert c.get("/health/live").status_code == 200


# ------------------------------------------------------------------------------------------ generated client
def test_generated_client_calls_running_server(tmp_path, live):
    out = tmp_path / "client"
    cfg = tmp_path / "config.yaml"
    cfg.write_text("post_hooks: []\nproject_name_override: gpnarx-client\npackage_name_override: gpnarx_client\n")
    import shutil

    exe = shutil.which("openapi-python-client")
    if exe is None:  # pragma: no cover
        pytest.skip("openapi-python-client is not installed")
    proc = subprocess.run([exe, "generate", "--path", str(ROOT / "openapi" / "openapi.json"), "--output-path",
                           str(out), "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # a clean generation: the NPZ bodies are documented in a content type the generator knows (no warning)
    assert "warning" not in (proc.stdout + proc.stderr).lower(), proc.stdout + proc.stderr
    sys.path.insert(0, str(out))
    try:
        gc = importlib.import_module("gpnarx_client")
        from gpnarx_client.api.models import list_models
        from gpnarx_client.api.predict import batch, predict
        from gpnarx_client.models import BatchItem, BatchRequest, Problem, RecordRequest

        client = gc.Client(base_url=str(live.base_url), timeout=httpx.Timeout(60.0))
        models = list_models.sync(client=client)
        assert sorted(m.name for m in models.models) == ["boucwen", "plain"]
        u, y = short_record(64, 3)
        res = predict.sync(client=client, name="boucwen", body=RecordRequest(u=u.tolist(), fs=FS, y=y.tolist(),
                                                                             mc_paths=32, seed=0))
        assert len(res.mean) == 64 and res.coverage >= 0 and res.version == "2"
        import io as _io

        from gpnarx_client.types import File

        buf = _io.BytesIO()
        np.savez(buf, u=u, y=y, fs=FS, units_u=np.str_("N"))
        npz_res = predict.sync(client=client, name="boucwen", body=File(payload=_io.BytesIO(buf.getvalue())),
                               mc_paths=32, seed=0)  # an NPZ record file as the body, the rest in the query
        assert npz_res.mean == res.mean
        bad = predict.sync_detailed(client=client, name="boucwen", body=RecordRequest(u=u.tolist(), fs=700.0))
        assert bad.status_code == 422 and isinstance(bad.parsed, Problem) and bad.parsed.field == "fs"
        items = [BatchItem(model="boucwen", u=u.tolist(), fs=FS, mc_paths=16),
                 BatchItem(model="nope", u=u.tolist(), fs=FS)]
        out_b = batch.sync(client=client, body=BatchRequest(requests=items))
        assert len(out_b.results[0].mean) == 64
        assert isinstance(out_b.results[1], Problem) and out_b.results[1].status == 404
    finally:
        sys.path.remove(str(out))
        for m in [m for m in sys.modules if m == "gpnarx_client" or m.startswith("gpnarx_client.")]:
            del sys.modules[m]


def test_settings_from_env():
    s = Settings.from_env({"GPNARX_MAX_SAMPLES": "1_000", "GPNARX_API_KEY": "k", "GPNARX_QUEUE_SIZE": "0"})
    assert s.max_samples == 1000 and s.api_key == "k" and s.queue_size == 0
    with pytest.raises(ValueError, match="GPNARX_MAX_BATCH"):
        Settings.from_env({"GPNARX_MAX_BATCH": "lots"})
    with pytest.raises(ValueError, match="mc_paths_default"):
        Settings(mc_paths_default=10, mc_paths_max=5)
    assert Settings.from_env({"GPNARX_API_KEY": "  "}).api_key is None


def test_truncated_and_changed_bundles_refused(tmp_path):
    root = copy_registry(tmp_path / "reg")
    npy = sorted((root / "boucwen" / "1").glob("*.npy"))[0]
    npy.write_bytes(npy.read_bytes()[:40])  # truncated
    mf = root / "boucwen" / "2" / "manifest.json"
    m = json.loads(mf.read_text())
    m["fs"] = 751.0  # manifest edited: its checksum (manifest.sha256) no longer matches
    mf.write_text(json.dumps(m))
    c = TestClient(create_app(root, settings()), raise_server_exceptions=False)
    ready = c.get("/health/ready").json()
    assert sorted(r["path"] for r in ready["refused"]) == ["boucwen/1", "boucwen/2"]
    assert ready["models"] == {"plain": ["1"]}
    assert_problem(c.post("/v1/models/boucwen/predict", json=rec(n=8)[0]), 404, "name")
    assert c.post("/v1/models/plain/predict", json=rec(n=8)[0]).status_code == 200


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGHUP"), reason="needs SIGHUP")
def test_cli_serve_subprocess_and_sighup_reload(tmp_path):
    import signal
    import socket

    from gpnarx.storage.bundle import save_bundle

    root = copy_registry(tmp_path / "reg")
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("GPNARX_API_KEY", None)
    proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--registry", str(root), "--port",
                             str(port), "--log-level", "warning"], cwd=str(ROOT), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        def up():
            assert proc.poll() is None, proc.stderr.read()
            try:
                return httpx.get(url + "/health/ready", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        _wait(up, timeout=60)
        assert httpx.get(url + "/v1/models/boucwen", timeout=10).json()["versions"] == ["1", "2"]
        save_bundle(built_registry().model, root, "boucwen", "3", fs=FS, units={"u": "N", "y": "m"}, training={})
        proc.send_signal(signal.SIGHUP)
        _wait(lambda: httpx.get(url + "/v1/models/boucwen", timeout=10).json()["versions"] == ["1", "2", "3"],
              timeout=30)
        r = httpx.post(url + "/v1/models/boucwen/predict", json=rec(n=16)[0], timeout=30)
        assert r.status_code == 200 and r.json()["version"] == "3" and "compute;dur=" in r.headers["server-timing"]
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()


def test_model_detail_reports_a_held_out_noise_calibration(tmp_path):
    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.bundle import save_bundle

    u, y = short_record(600, 1)
    u2, y2 = short_record(300, 2)
    y2 = y2 + 0.05 * np.std(y2) * np.random.default_rng(0).normal(size=y2.size)
    m = GPNARX(ny=4, nu=4, max_train_points=300, n_restarts=0).fit([(u, y)], heldout=[(u2, y2)])
    save_bundle(m, tmp_path, "cal", fs=FS, units={"u": "N", "y": "m"})
    c = TestClient(create_app(tmp_path, settings()), raise_server_exceptions=False)
    d = c.get("/v1/models/cal").json()
    assert d["noise_calibration"]["method"] == "heldout_ml"
    assert d["noise_calibration"]["noise_var"] == pytest.approx(m.noise_var_)
    assert d["hyperparameters"]["noise_var"] == pytest.approx(m.noise_var_)


def test_backend_in_the_body_picks_the_free_runs_array_backend(client, monkeypatch):
    """"backend": "jax" runs the free run on the JAX backend and the answer says so (linearised: numpy's
    numbers to rounding); a backend that is not one of numpy/jax, or jax on a server without it, is a 422
    naming the field."""
    pytest.importorskip("jax")
    from gpnarx.operations import base as operations_base

    body, _ = rec()
    body["method"] = "linear"
    a = client.post("/v1/models/boucwen/predict", json=body).json()
    b = client.post("/v1/models/boucwen/predict", json={**body, "backend": "jax"}).json()
    assert a["backend"] == "numpy" and b["backend"] == "jax"
    assert np.allclose(b["mean"], a["mean"], rtol=1e-7, atol=1e-12) and np.allclose(b["upper"], a["upper"], rtol=1e-6)
    r = client.post("/v1/models/boucwen/predict", json={**body, "backend": "cuda"})
    assert r.status_code == 422 and "backend" in r.text
    monkeypatch.setattr(operations_base, "jax_available", lambda: False)
    r = client.post("/v1/models/boucwen/predict", json={**body, "backend": "jax"})
    assert r.status_code == 422 and r.json()["field"] == "backend" and "not installed" in r.json()["detail"]
