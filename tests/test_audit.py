"""The audit trail (service.audit): one JSON line per novelty verdict, written off the request path."""
from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, multisine, noisy, simulate

from gpnarx.service.app import create_app
from gpnarx.service.audit import AuditTrail, client_id, record_sha256
from gpnarx.service.settings import Settings

FIELDS = {"time", "request_id", "client", "operation", "slot", "model", "version", "record_sha256", "n_samples",
          "score", "threshold", "verdict", "out_of_range", "diverged_paths"}


@pytest.fixture(scope="module")
def registry():
    return built_registry().root


def _records(n: int, length: int = 256):
    out = []
    for k in range(n):
        u = multisine(length, 40 + k)
        out.append({"u": u.tolist(), "y": noisy(simulate(u), 40 + k).tolist(), "fs": FS, "mc_paths": 16,
                    "seed": 0})
    return out


def _lines(path: Path) -> list[dict]:
    return [json.loads(s) for s in path.read_text().splitlines()]


def _app(registry, **kw):
    return create_app(registry, Settings(workers=1, queue_size=4, registry_poll=0, **kw))


def test_single_and_batch_novelty_calls_write_one_line_each_with_their_request_ids(registry, tmp_path):
    target = tmp_path / "audit" / "trail.jsonl"
    target.parent.mkdir()
    recs = _records(3)
    app = _app(registry, audit_log=str(target), api_key="k-plant-7")
    with TestClient(app) as c:
        answers = []
        for i, rec in enumerate(recs[:2]):
            r = c.post("/v1/models/boucwen/novelty", json=rec, headers={"X-Request-ID": f"single-{i}", "X-API-Key":
                                                                          "k-plant-7"})
            assert r.status_code == 200, r.text
            answers.append(r.json())
        body = {"requests": [{"model": "boucwen", "operation": "novelty", **rec} for rec in recs]
                + [{"model": "boucwen", "operation": "predict", **recs[0]},  # not audited by default
                   {"model": "nope", "operation": "novelty", **recs[0]}]}  # a failed slot: no verdict, no line
        r = c.post("/v1/batch", json=body, headers={"X-Request-ID": "batch-1", "X-API-Key": "k-plant-7"})
        assert r.status_code == 200
        slots = r.json()["results"]
        assert app.state.service.telemetry.audit.flush()
    lines = _lines(target)
    assert [(x["request_id"], x["slot"]) for x in lines] == [
        ("single-0", None), ("single-1", None), ("batch-1", 0), ("batch-1", 1), ("batch-1", 2)]
    key_id = hashlib.sha256(b"k-plant-7").hexdigest()[:12]
    for x, ans, rec in zip(lines, answers + slots[:3], recs[:2] + recs):
        assert set(x) == FIELDS
        assert x["client"] == key_id and "k-plant-7" not in json.dumps(x)
        assert (x["model"], x["version"], x["operation"]) == ("boucwen", ans["version"], "novelty")
        assert x["score"] == pytest.approx(ans["score"]) and x["threshold"] == pytest.approx(ans["threshold"])
        assert x["verdict"] == ans["verdict"] and x["out_of_range"] == ans["out_of_range"]
        assert x["diverged_paths"] == ans["diverged_paths"] and x["n_samples"] == len(rec["u"])
        assert x["record_sha256"] == record_sha256(rec["u"], rec["y"])
        assert x["time"].endswith("Z")
    assert len({x["record_sha256"] for x in lines[2:]}) == 3  # three different records


def test_record_sha256_is_of_float64_bytes():
    u, y = [1, 2, 3], [0.5, -1.0, 2.0]
    expect = hashlib.sha256(np.array(u, "<f8").tobytes() + np.array(y, "<f8").tobytes()).hexdigest()
    assert record_sha256(u, y) == expect
    assert record_sha256(u) != expect
    assert client_id(None) == "anonymous" and len(client_id("secret")) == 12


def test_predicts_are_audited_when_configured(registry, tmp_path):
    target = tmp_path / "trail.jsonl"
    rec = _records(1, 128)[0]
    app = _app(registry, audit_log=str(target), audit_predicts=True)
    with TestClient(app) as c:
        assert c.post("/v1/models/boucwen/predict", json=rec, headers={"X-Request-ID": "p-1"}).status_code == 200
        assert c.post("/v1/models/boucwen/loops", json=rec).status_code == 200  # loops are never audited
        assert app.state.service.telemetry.audit.flush()
    (line,) = _lines(target)
    assert line["request_id"] == "p-1" and line["operation"] == "predict" and line["client"] == "anonymous"
    assert line["score"] is None and line["verdict"] is None


def test_an_unwritable_target_loses_no_answer_and_shows_on_metrics_and_ready(registry, tmp_path, caplog):
    blocked = tmp_path / "ro"
    blocked.mkdir()
    target = blocked / "trail.jsonl"
    os.chmod(blocked, 0o500)
    if os.access(blocked, os.W_OK):  # root ignores the mode: a directory as the target is unwritable for all
        target = tmp_path / "is-a-directory"
        target.mkdir()
    recs = _records(4, 128)
    app = _app(registry, audit_log=str(target))
    try:
        with TestClient(app) as c:
            for i, rec in enumerate(recs):
                r = c.post("/v1/models/boucwen/novelty", json=rec, headers={"X-Request-ID": f"n-{i}"})
                assert r.status_code == 200 and r.json()["verdict"] in ("healthy", "novel"), r.text
            r = c.post("/v1/batch", json={"requests": [{"model": "boucwen", "operation": "novelty", **rec}
                                                       for rec in recs[:2]]})
            assert r.status_code == 200 and all("verdict" in x for x in r.json()["results"])
            assert app.state.service.telemetry.audit.flush()
            ready = c.get("/health/ready")
            assert ready.status_code == 200 and ready.json()["status"] == "ready"
            audit = ready.json()["audit"]
            assert audit["ok"] is False and audit["failed"] == 6 and audit["written"] == 0
            assert audit["last_error"] and audit["target"] == str(target)
            metrics = c.get("/metrics").text
            assert 'gpnarx_audit_lines_total{outcome="failed"} 6.0' in metrics
            assert 'gpnarx_audit_lines_total{outcome="written"} 0.0' in metrics
            assert "gpnarx_audit_write_failures_total " in metrics
            failed = [r for r in caplog.records if r.name == "gpnarx.service.audit" and r.levelname == "ERROR"]
            assert failed and failed[0].request_id == "n-0"  # the log line names the first lost line's request
    finally:
        os.chmod(blocked, 0o700)


def test_a_slow_target_never_delays_an_answer_and_a_full_queue_drops_and_counts(monkeypatch):
    trail = AuditTrail("-", queue_size=2)
    gate = []

    def stuck(lines):  # a target that hangs (a stalled network mount)
        while not gate:
            time.sleep(0.01)

    monkeypatch.setattr(trail, "_write", stuck)
    out = {"model": "m", "version": "1", "score": 1.0, "threshold": 2.0, "verdict": "healthy", "out_of_range": [],
           "diverged_paths": 0}

    class Req:
        u, y = [1.0, 2.0], [0.0, 1.0]

    t0 = time.perf_counter()
    for _ in range(50):
        trail.record("novelty", out, Req, "r", "anonymous")
    assert time.perf_counter() - t0 < 1.0
    st = trail.status()
    assert st["queued"] == 2 and st["dropped"] >= 44  # a few taken by the stuck writer, two queued, the rest dropped
    gate.append(1)
    trail.close(timeout=2)


def test_a_target_that_recovers_writes_again(tmp_path):
    target = tmp_path / "later" / "trail.jsonl"  # the folder does not exist yet
    trail = AuditTrail(str(target))
    out = {"model": "m", "version": "1", "score": 1.0, "threshold": 2.0, "verdict": "healthy"}

    class Req:
        u, y = [1.0], [2.0]

    trail.record("novelty", out, Req, "a", "anonymous")
    assert trail.flush() and trail.status()["failed"] == 1 and trail.status()["ok"] is False
    target.parent.mkdir()
    trail.record("novelty", out, Req, "b", "anonymous")
    assert trail.flush() and trail.status()["written"] == 1 and trail.status()["ok"] is True
    trail.close()
    assert [x["request_id"] for x in _lines(target)] == ["b"]


def test_off_writes_nothing_and_fsspec_urls_are_targets(tmp_path):
    off = AuditTrail("off")
    assert not off.wants("novelty") and off.status()["target"] == "off"
    url = "file://" + str(tmp_path / "t.jsonl")
    trail = AuditTrail(url)

    class Req:
        u, y = [1.0], None

    trail.record("novelty", {"model": "m", "verdict": "novel"}, Req, "u-1", "anonymous")
    trail.close()
    assert _lines(tmp_path / "t.jsonl")[0]["request_id"] == "u-1"
    mem = AuditTrail("memory://audit/t.jsonl")
    mem.record("novelty", {"model": "m", "verdict": "novel"}, Req, "m-1", "anonymous")
    mem.close()
    import fsspec

    with fsspec.open("memory://audit/t.jsonl", "r") as fh:
        assert json.loads(fh.read().splitlines()[0])["request_id"] == "m-1"
    assert AuditTrail("s3://user:pw@bucket/a.jsonl").status()["target"] == "s3://bucket/a.jsonl"


def test_stdout_is_the_default_target_and_read_at_each_write(capsys):
    trail = AuditTrail(None)

    class Req:
        u, y = [1.0], [2.0]

    assert trail.status()["target"] == "stdout"
    trail.record("novelty", {"model": "m", "verdict": "healthy"}, Req, "s-1", "anonymous")
    assert trail.flush()
    assert json.loads(capsys.readouterr().out)["request_id"] == "s-1"
    trail.record("novelty", {"model": "m", "verdict": "healthy"}, Req, "s-2", "anonymous")  # a new capture
    trail.close()
    assert json.loads(capsys.readouterr().out)["request_id"] == "s-2" and trail.status()["failed"] == 0


def test_offloaded_hashing_writes_the_same_line_and_is_bounded(tmp_path, monkeypatch):
    import gpnarx.service.audit as audit_mod

    target = tmp_path / "t.jsonl"
    trail = AuditTrail(str(target))

    class Req:
        u, y = list(np.arange(1000.0)), list(np.ones(1000))

    out = {"model": "m", "version": "1", "score": 0.5, "threshold": 1.0, "verdict": "healthy"}
    trail.record("novelty", out, Req, "off-1", "anonymous", offload=True)
    trail.record("novelty", out, Req, "in-1", "anonymous")
    assert trail.flush()
    lines = {x["request_id"]: x for x in _lines(target)}
    assert lines["off-1"]["record_sha256"] == lines["in-1"]["record_sha256"] == record_sha256(Req.u, Req.y)
    gate = []
    monkeypatch.setattr(audit_mod, "MAX_HASHING", 2)
    real = trail._record

    def slow(*a):  # the hash thread is stuck: at most MAX_HASHING records wait, the rest are dropped
        while not gate:
            time.sleep(0.01)
        real(*a)

    monkeypatch.setattr(trail, "_record", slow)
    t0 = time.perf_counter()
    for i in range(10):
        trail.record("novelty", out, Req, f"b-{i}", "anonymous", offload=True)
    assert time.perf_counter() - t0 < 1.0 and trail.status()["dropped"] == 8
    gate.append(1)
    trail.close()
    assert sorted(x["request_id"] for x in _lines(target) if x["request_id"].startswith("b-")) == ["b-0", "b-1"]
