"""Edge-case inputs listed in the README that the other service tests do not send on their own.

- 1- and 2-sample records (shorter than the model's lags, ny = nu = 10) on predict, loops,
  novelty and batch: answered 200 with arrays of that length (the free run starts from rest);
- huge but finite numbers (1e300, -1e308) that make the free run overflow: 422 naming ``u``;
  large values that stay finite (1e30): 200 with finite arrays or a 422 problem, never a 5xx;
- unknown model or version on every POST operation and in a batch slot: 404 naming the field.
"""
from __future__ import annotations

import json
import math

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

PROBLEM = "application/problem+json"
OPS = ("predict", "loops", "novelty")


@pytest.fixture(scope="module")
def client():
    return TestClient(create_app(built_registry().root, Settings(workers=1, queue_size=4)),
                      raise_server_exceptions=False)


def _problem(r, status, field):
    assert r.status_code == status, r.text[:300]
    assert r.headers["content-type"].startswith(PROBLEM)
    p = r.json()
    assert p["status"] == status and p["field"] == field and p["detail"], p
    assert "Traceback" not in r.text
    return p


def _finite(d):
    if isinstance(d, dict):
        return all(_finite(v) for v in d.values())
    if isinstance(d, list):
        return all(_finite(v) for v in d)
    return not isinstance(d, float) or math.isfinite(d)


@pytest.mark.parametrize("n", [1, 2])
@pytest.mark.parametrize("op", OPS)
def test_records_shorter_than_the_lags(client, op, n):
    body = {"u": [0.5, -0.25][:n], "y": [1e-5, -1e-5][:n], "fs": FS, "mc_paths": 8, "seed": 0}
    r = client.post(f"/v1/models/boucwen/{op}", json=body)
    assert r.status_code == 200, r.text[:300]
    d = r.json()
    assert _finite(d)
    if op == "predict":
        assert all(len(d[k]) == n for k in ("mean", "lower", "upper", "std"))
        assert d["coverage"] is not None and 0 <= d["coverage"] <= 100
    elif op == "loops":
        assert d["n_samples"] == n and len(d["predicted"]["x"]) == n and len(d["measured"]["force"]) == n
    else:
        assert d["n_samples"] >= 1 and d["verdict"] in ("healthy", "novel")
    res = client.post("/v1/batch", json={"requests": [{"model": "boucwen", "operation": op, **body}]}).json()
    assert "status" not in res["results"][0], res


@pytest.mark.parametrize("value", [1e300, -1e308])
@pytest.mark.parametrize("op", OPS)
def test_huge_values_that_overflow_are_a_422_on_u(client, op, value):
    body = {"u": [value, -value] * 20, "y": [value] * 40, "fs": FS, "mc_paths": 8}
    p = _problem(client.post(f"/v1/models/boucwen/{op}", json=body), 422, "u")
    assert "diverged" in p["detail"]


@pytest.mark.parametrize("op", OPS)
def test_large_finite_values_never_5xx(client, op):
    body = {"u": [1e30, -1e30] * 20, "y": [1e30] * 40, "fs": FS, "mc_paths": 8}
    r = client.post(f"/v1/models/boucwen/{op}", json=body)
    assert r.status_code in (200, 422), r.text[:300]
    if r.status_code == 200:
        assert _finite(r.json())
    else:
        _problem(r, 422, "u")


@pytest.mark.parametrize("op", OPS)
def test_unknown_model_or_version(client, op):
    body = {"u": [0.5] * 16, "y": [0.0] * 16, "fs": FS, "mc_paths": 8}
    p = _problem(client.post(f"/v1/models/nosuchmodel/{op}", json=body), 404, "name")
    assert "nosuchmodel" in p["detail"] and "boucwen" in p["detail"]  # names what exists
    p = _problem(client.post(f"/v1/models/boucwen/versions/99/{op}", json=body), 404, "version")
    assert "99" in p["detail"]
    res = client.post("/v1/batch", json={"requests": [
        {"model": "nosuchmodel", "operation": op, **body},
        {"model": "boucwen", "version": "99", "operation": op, **body},
        {"model": "boucwen", "version": "1", "operation": op, **body}]}).json()["results"]
    assert res[0]["status"] == 404 and res[0]["field"] == "requests.0.model"
    assert res[1]["status"] == 404 and res[1]["field"] == "requests.1.version"
    assert "status" not in res[2] and res[2]["version"] == "1"


@pytest.mark.parametrize("ctype", [None, "text/plain", "application/x-www-form-urlencoded"])
def test_a_record_body_without_a_json_or_npz_content_type_is_a_problem_naming_the_header(client, ctype):
    import json

    body = json.dumps({"u": [0.0, 1.0, 0.5], "fs": FS}).encode()
    headers = {} if ctype is None else {"content-type": ctype}
    for op in OPS:
        p = _problem(client.post(f"/v1/models/boucwen/{op}", content=body, headers=headers), 422,
                     "content-type")
        assert "content-type: application/json or application/x-npz or application/octet-stream" in p["detail"], p
        assert (ctype or "no content-type header") in p["detail"]
        assert p["accepted"] == ["application/json", "application/x-npz", "application/octet-stream"]
    # the same body with its header is answered; a +json type is JSON too
    for good in ("application/json", "application/merged-patch+json"):
        r = client.post("/v1/models/boucwen/predict", content=body, headers={"content-type": good})
        assert r.status_code == 200, r.text[:300]


@pytest.mark.parametrize("token", ["1e400", "NaN", "-Infinity"])
def test_a_non_finite_number_in_one_batch_record_fails_that_record_only(client, token):
    """JSON that holds a number beyond the float range (valid JSON) or a NaN / Infinity token in one record:
    that record's 422 in its slot, the others answered."""
    good = {"model": "boucwen", "u": [0.5, -0.25] * 16, "fs": FS, "method": "linear"}
    body = json.dumps({"requests": [good, good, good]})
    at = body.index('"u": [', body.index("}") + 1)  # the second record's u
    body = body[:at] + f'"u": [{token}, ' + body[at + len('"u": ['):]
    r = client.post("/v1/batch", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 200, r.text[:300]
    res = r.json()["results"]
    assert "status" not in res[0] and "status" not in res[2], res
    assert res[1]["status"] == 422 and res[1]["field"] == "requests.1.u.0", res[1]
    # the record routes answer the same number the same way
    one = json.dumps(good).replace('"u": [', f'"u": [{token}, ', 1)
    _problem(client.post("/v1/models/boucwen/predict", content=one, headers={"content-type": "application/json"}),
             422, "u.0")


def test_a_measured_start_far_outside_the_trained_range_is_named(client):
    """Loops whose restoring force overflows because of the measured start blame y0 (or y), not a u inside the
    trained range; a u far outside it is still named."""
    u = [0.5, -0.25] * 32
    r = client.post("/v1/models/boucwen/loops", json={"u": u, "y0": [1e308] * 64, "y": [0.0] * 64, "fs": FS,
                                                      "method": "linear"})
    p = _problem(r, 422, "y0")
    assert "y0" in p["detail"] and "output range" in p["detail"]
    r = client.post("/v1/models/boucwen/loops", json={"u": u, "y": [1e308] * 64, "start": "measured", "fs": FS,
                                                      "method": "linear"})
    p = _problem(r, 422, "y")
    assert "first ny" in p["detail"]
    r = client.post("/v1/models/boucwen/loops", json={"u": [1e300, -1e300] * 32, "y0": [1e308] * 64, "fs": FS,
                                                      "method": "linear"})
    _problem(r, 422, "u")


def test_confidence_next_to_one_is_answered(client):
    c = 0.9999999999999999  # the largest double below 1: the schema takes it
    r = client.post("/v1/models/boucwen/predict", json={"u": [0.5] * 32, "fs": FS, "method": "linear",
                                                       "confidence": c})
    assert r.status_code == 200, r.text[:300]
    d = r.json()
    assert d["confidence"] == c and all(lo <= m <= hi for lo, m, hi in zip(d["lower"], d["mean"], d["upper"]))


def test_an_fs_mismatch_prints_both_values_apart(client):
    from gpnarx.model.record import FS_RTOL

    off = FS * (1 - 1.5 * FS_RTOL)  # just outside the tolerance: both rates printed apart
    p = _problem(client.post("/v1/models/boucwen/predict", json={"u": [0.5] * 32, "fs": off}), 422, "fs")
    assert f"{off:.12g}" in p["detail"] and f"model's fs {FS:.12g} Hz" in p["detail"]


def test_the_answers_start_says_how_the_run_started(client):
    ny = built_registry().model.ny
    u, y = [0.5, -0.25] * 32, [1e-5, -1e-5] * 32
    base = {"u": u, "fs": FS, "method": "linear"}
    post = lambda **kw: client.post("/v1/models/boucwen/predict", json={**base, **kw})  # noqa: E731
    assert post().json()["start"] == "rest"
    assert post(y0=y[:ny]).json()["start"] == "measured"  # y0 starts the run from measured outputs
    assert post(y=y, start="measured").json()["start"] == "measured"
    # too short to hold a measured start: the run starts at rest, and says so
    short = client.post("/v1/models/boucwen/predict", json={"u": u[:ny], "y": y[:ny], "fs": FS, "method": "linear",
                                                            "start": "measured"})
    assert short.status_code == 200 and short.json()["start"] == "rest", short.text[:300]
    p = _problem(post(y0=y[:ny], start="rest"), 422, "start")
    assert "contradict" in p["detail"]


def test_a_spike_far_outside_the_range_still_gets_a_numeric_score(client):
    """One sample some 1e160 from the prediction: the novelty score (an RMS taken without overflow) is a number,
    the verdict novel; predict's fit and rmse are numbers too."""
    n = 256
    u = [0.5, -0.25] * (n // 2)
    y = [0.0] * n
    y[200] = 1e160
    d = client.post("/v1/models/boucwen/novelty", json={"u": u, "y": y, "fs": FS, "method": "linear",
                                                        "start": "rest"}).json()
    assert isinstance(d["score"], float) and d["score"] > 1e150 and d["verdict"] == "novel", d
    assert "y" in d["out_of_range"]
    p = client.post("/v1/models/boucwen/predict", json={"u": u, "y": y, "fs": FS, "method": "linear"}).json()
    assert isinstance(p["rmse"], float) and p["rmse"] > 1e150 and isinstance(p["fit"], float), p.get("rmse")


def test_strict_flags_empty_batch_and_long_echoes(client):
    """return_state takes only true/false; an empty batch body is the record routes' 422 body; a problem that
    quotes a 4000-digit number stays short."""
    body = {"u": [0.5] * 32, "fs": FS, "method": "linear"}
    for v in ("yes", 1, "true"):
        _problem(client.post("/v1/models/boucwen/predict", json={**body, "return_state": v}), 422, "return_state")
    _problem(client.post("/v1/batch", content=b"", headers={"content-type": "application/json"}), 422, "body")
    r = client.post("/v1/models/boucwen/predict", content=b'{"fs": 750, "u": [0.5], "mc_paths": ' + b"9" * 4000 + b"}",
                    headers={"content-type": "application/json"})
    p = _problem(r, 422, "mc_paths")
    assert len(p["detail"]) <= 600 and "characters)" in p["detail"]
