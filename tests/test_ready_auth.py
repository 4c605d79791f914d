"""/health/ready behind an API key: open readiness (status and counts), details only for the key.

With ``GPNARX_API_KEY`` set, ``/v1/models`` needs the key; ``/health/ready`` stays open for probes, so it
must not list what ``/v1/models`` hides (models, versions, refused bundle paths, the audit target).
"""
from __future__ import annotations

import shutil

from fastapi.testclient import TestClient
from test_service_support import built_registry

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

KEY = "s3cret-key"


def _settings(**kw):
    return Settings(workers=1, queue_size=2, registry_poll=0, **kw)


def _registry_with_a_refused_bundle(tmp_path):
    reg = tmp_path / "reg"
    shutil.copytree(built_registry().root, reg)
    bad = reg / "boucwen" / "1" / "theta.npy"
    bad.write_bytes(bad.read_bytes()[:-8] + b"\0" * 8)  # refused by its checksum
    return reg


def test_unauthenticated_ready_answers_readiness_and_counts_only(tmp_path):
    reg = _registry_with_a_refused_bundle(tmp_path)
    audit = tmp_path / "private-audit-folder" / "trail.jsonl"
    app = create_app(reg, _settings(api_key=KEY, audit_log=str(audit)))
    with TestClient(app) as c:
        r = c.get("/health/ready")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body == {"status": "ready", "bundles": 2, "refused_count": 1}
        for secret in ("boucwen", "plain", "private-audit-folder", "theta"):
            assert secret not in r.text
        for wrong in ("wrong", ""):
            assert c.get("/health/ready", headers={"X-API-Key": wrong}).json() == body
        full = c.get("/health/ready", headers={"X-API-Key": KEY})
        assert full.status_code == 200
        f = full.json()
        assert f["models"] == {"boucwen": ["2"], "plain": ["1"]} and f["refused_count"] == 1
        assert f["refused"][0]["path"] == "boucwen/1" and f["audit"]["target"] == str(audit)
        assert c.head("/health/ready").status_code == 200


def test_without_a_key_ready_keeps_its_details(tmp_path):
    app = create_app(built_registry().root, _settings())
    with TestClient(app) as c:
        body = c.get("/health/ready").json()
    assert body["models"]["boucwen"] == ["1", "2"] and body["refused"] == [] and body["refused_count"] == 0
    assert "audit" in body


def test_unauthenticated_not_ready_problem_hides_paths_and_errors(tmp_path):
    reg = tmp_path / "reg"
    shutil.copytree(built_registry().root / "plain", reg / "plain")
    (reg / "plain" / "1" / "manifest.json").write_text("{}")  # refused: nothing loaded
    app = create_app(reg, _settings(api_key=KEY))
    c = TestClient(app, raise_server_exceptions=False)
    r = c.get("/health/ready")
    assert r.status_code == 503 and r.headers["Retry-After"]
    p = r.json()
    assert p["bundles"] == 0 and p["refused_count"] == 1
    assert "refused" not in p and "audit" not in p and "plain" not in r.text and "manifest" not in r.text
    full = c.get("/health/ready", headers={"X-API-Key": KEY}).json()
    assert full["refused"][0]["path"] == "plain/1" and "audit" in full
