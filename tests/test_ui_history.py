"""GET /v1/models/{name}/novelty/history: a model's novelty verdicts read back from the audit trail (the /ui
page's trend), with the trail written by the real writer (service.audit) from novelty calls, and the reader
(service.audit_history) tolerant of lines cut short or damaged, and bounded in what it reads."""
from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.service.app import create_app
from gpnarx.service.audit_history import lines_backwards, novelty_history
from gpnarx.service.routers.history import LIMIT_MAX
from gpnarx.service.settings import Settings

HISTORY = "/v1/models/boucwen/novelty/history"


@pytest.fixture(scope="module")
def registry():
    return built_registry().root


def _app(registry, **kw):
    return create_app(registry, Settings(workers=1, queue_size=4, registry_poll=0, **kw))


def _records(n: int):
    out = []
    for k in range(n):
        u, y = short_record(192, 60 + k)
        if k == n - 1:
            y = 1.3 * y  # a changed structure: novel
        out.append({"u": u.tolist(), "y": y.tolist(), "fs": FS, "mc_paths": 16, "seed": 0})
    return out


@pytest.fixture(scope="module")
def trail(registry, tmp_path_factory):
    """An audit trail written by the service (service.audit) from novelty calls on boucwen: three single calls
    and a batch of two (versions 1 and 2, the second slot the first record again); the trail and the answers."""
    target = tmp_path_factory.mktemp("hist") / "audit.jsonl"
    app = _app(registry, audit_log=str(target))
    answers = []
    with TestClient(app) as c:
        recs = _records(4)
        for i, rec in enumerate(recs[:3]):
            r = c.post("/v1/models/boucwen/novelty", json=rec, headers={"X-Request-ID": f"h-{i}"})
            assert r.status_code == 200, r.text
            answers.append(r.json())
        r = c.post("/v1/batch", json={"requests": [{"model": "boucwen", "version": "1", "operation": "novelty",
                                                    **recs[3]},
                                                   {"model": "boucwen", "operation": "novelty", **recs[0]}]},
                   headers={"X-Request-ID": "h-batch"})
        assert r.status_code == 200
        answers += r.json()["results"]
        assert app.state.service.telemetry.audit.flush()
    assert len(target.read_text().splitlines()) == 5
    return target, answers


def test_history_lists_the_audited_verdicts_oldest_first(registry, trail):
    target, answers = trail
    with TestClient(_app(registry, audit_log=str(target))) as c:
        r = c.get(HISTORY)
        assert r.status_code == 200, r.text
        h = r.json()
    assert h["model"] == "boucwen" and h["available"] is True and h["reason"] is None
    assert h["source"] == "audit" and h["target"] == str(target) and h["limit"] == 200
    assert h["skipped_lines"] == 0 and h["older_unread"] is False and h["read_bytes"] == target.stat().st_size
    pts = h["points"]
    assert [p["request_id"] for p in pts] == ["h-0", "h-1", "h-2", "h-batch", "h-batch"]
    assert [p["slot"] for p in pts] == [None, None, None, 0, 1]
    for p, a in zip(pts, answers):
        assert p["score"] == pytest.approx(a["score"]) and p["threshold"] == pytest.approx(a["threshold"])
        assert p["verdict"] == a["verdict"] and p["version"] == a["version"]
        assert p["out_of_range"] == a["out_of_range"] and p["n_samples"] == 192
        assert p["time"].endswith("Z") and len(p["record_sha256"]) == 64
    assert [p["version"] for p in pts] == ["2", "2", "2", "1", "2"]
    assert "novel" in {p["verdict"] for p in pts} and "healthy" in {p["verdict"] for p in pts}
    assert pts[0]["record_sha256"] == pts[4]["record_sha256"]  # the same record sent twice
    assert [p["time"] for p in pts] == sorted(p["time"] for p in pts)


def test_limit_keeps_the_newest_and_is_bounded(registry, trail):
    target, _ = trail
    with TestClient(_app(registry, audit_log=str(target))) as c:
        pts = c.get(HISTORY, params={"limit": 2}).json()["points"]
        assert [(p["request_id"], p["slot"]) for p in pts] == [("h-batch", 0), ("h-batch", 1)]
        for bad in (0, LIMIT_MAX + 1, "many"):
            r = c.get(HISTORY, params={"limit": bad})
            assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
            assert r.json()["field"] == "limit" and "limit" in r.json()["detail"]
        assert c.get(HISTORY, params={"limit": LIMIT_MAX}).status_code == 200
        r = c.get("/v1/models/nope/novelty/history")
        assert r.status_code == 404 and r.json()["field"] == "name"
        assert c.get("/v1/models/plain/novelty/history").json()["points"] == []  # a model with no verdict


def test_damaged_and_partial_lines_are_skipped(registry, trail, tmp_path):
    """What a live trail can hold: a line cut short by a crash (the next line appended after it), a line that is
    not JSON, a JSON line that is not an audit line, a verdict with a wrong field, blank lines, and a last line
    still being written (no newline yet: not counted as damaged)."""
    target, _ = trail
    good = target.read_text().splitlines()
    damaged = tmp_path / "damaged.jsonl"
    other = json.loads(good[0]) | {"model": "other"}
    wrong = json.loads(good[1]) | {"verdict": "maybe"}
    predict = json.loads(good[1]) | {"operation": "predict", "verdict": None, "score": None}
    text = "\n".join([good[0], good[1][: len(good[1]) // 2] + good[2],  # cut short, the next line after it
                      "not json at all", "[1, 2, 3]", "", json.dumps(other), json.dumps(wrong), json.dumps(predict)])
    damaged.write_bytes(text.encode() + b"\n\xff\xfe{not utf-8}\n" + "\n".join(good[3:5]).encode() + b"\n"
                        + good[2][:40].encode())
    with TestClient(_app(registry, audit_log=str(damaged))) as c:
        h = c.get(HISTORY).json()
    assert [(p["request_id"], p["slot"]) for p in h["points"]] == [("h-0", None), ("h-batch", 0), ("h-batch", 1)]
    # cut short with the next line after it, not JSON, a list, not UTF-8; the last line, still being written, is not
    assert h["skipped_lines"] == 4


def test_the_read_is_bounded(trail, tmp_path):
    target, _ = trail
    lines = target.read_text().splitlines()
    big = tmp_path / "big.jsonl"
    filler = json.dumps(json.loads(lines[0]) | {"model": "another"})
    big.write_text("\n".join([lines[0]] + [filler] * 2000 + [lines[1]]) + "\n")
    size = big.stat().st_size
    h = novelty_history(str(big), "boucwen", 10, max_bytes=4096)
    assert [p["request_id"] for p in h.points] == ["h-1"]  # the first line lies beyond the bound
    assert h.older_unread is True and h.read_bytes <= 4096 and h.skipped_lines == 0
    h = novelty_history(str(big), "boucwen", 10, max_bytes=size)
    assert [p["request_id"] for p in h.points] == ["h-0", "h-1"] and h.older_unread is False
    assert h.read_bytes == size
    h = novelty_history(str(big), "boucwen", 1, max_bytes=size)  # stops at the newest one
    assert [p["request_id"] for p in h.points] == ["h-1"] and h.read_bytes < 1000


def test_lines_backwards_across_blocks(tmp_path):
    f = tmp_path / "t.txt"
    f.write_bytes(b"alpha\nbeta\n\ngamma-long-line\ndelta")
    with open(f, "rb") as fh:
        for block in (1, 2, 3, 7, 64):
            got = list(lines_backwards(fh, f.stat().st_size, block=block))
            assert got == [(b"delta", False), (b"gamma-long-line", True), (b"", True), (b"beta", True),
                           (b"alpha", True)], block
        # the last 12 bytes begin inside gamma's line, which is therefore not yielded
        assert list(lines_backwards(fh, f.stat().st_size, max_bytes=12, block=5)) == [(b"delta", False)]
        assert list(lines_backwards(fh, f.stat().st_size, max_bytes=22, block=5)) == [
            (b"delta", False), (b"gamma-long-line", True)]


@pytest.mark.parametrize("target,why", [(None, "stdout"), ("-", "stdout"), ("off", "off"),
                                        ("s3://bucket/audit.jsonl", "object store")])
def test_a_trail_not_in_a_local_file_has_no_history_and_says_why(registry, target, why):
    with TestClient(_app(registry, audit_log=target)) as c:
        h = c.get(HISTORY).json()
    assert h["available"] is False and h["points"] == [] and why in h["reason"]
    assert "s3://bucket" not in h["target"] or target.startswith("s3://")


def test_missing_file_and_api_key(registry, tmp_path):
    target = tmp_path / "none-yet.jsonl"
    with TestClient(_app(registry, audit_log=str(target), api_key="k-1")) as c:
        r = c.get(HISTORY)
        assert r.status_code == 401 and r.json()["field"] == "X-API-Key"
        h = c.get(HISTORY, headers={"X-API-Key": "k-1"}).json()
    assert h["available"] is True and h["points"] == [] and "no audit line written yet" in h["reason"]


def test_history_is_in_the_openapi_document(registry):
    with TestClient(_app(registry)) as c:
        doc = c.get("/openapi.json").json()
    op = doc["paths"]["/v1/models/{name}/novelty/history"]["get"]
    assert op["operationId"] == "novelty_history"
    limit = next(p for p in op["parameters"] if p["name"] == "limit")
    assert limit["schema"]["maximum"] == LIMIT_MAX and limit["schema"]["minimum"] == 1
    assert op["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/NoveltyHistory")

