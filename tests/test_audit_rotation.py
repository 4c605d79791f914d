"""The audit trail's file under rotation, deletion and failing writes: no line lost without a count,
no line torn.

- deleted while the server runs: the next line goes to a new file at the path (not to the deleted inode);
- renamed (logrotate without copytruncate): lines before go to the rotated file, later lines to a new file at
  the path, each once; with copytruncate the file is truncated in place and later lines start at its start;
- SIGHUP (``gpnarx serve``) reopens the file as well;
- a write that fails midway (a full disk) leaves no fragment: every line of the file parses, the lost line is
  counted (``failed``, ``lost``) on ``status()`` (/health/ready's ``audit``) and on /metrics.
"""
from __future__ import annotations

import asyncio
import errno
import json
import os
import signal
from pathlib import Path

import pytest

import gpnarx.service.audit as audit_mod
from gpnarx.service.audit import AuditTrail


class Req:
    u, y = [1.0, 2.0], [0.5, 0.25]


OUT = {"model": "m", "version": "1", "score": 0.5, "threshold": 1.0, "verdict": "healthy", "out_of_range": [],
       "diverged_paths": 0}


def _put(trail: AuditTrail, *ids: str) -> None:
    for rid in ids:
        trail.record("novelty", OUT, Req, rid, "anonymous")
    assert trail.flush()


def _ids(path: Path) -> list[str]:
    """The request ids of a trail file; every line must parse."""
    text = path.read_text()
    assert text == "" or text.endswith("\n"), repr(text[-80:])
    return [json.loads(line)["request_id"] for line in text.splitlines()]


def test_a_deleted_file_is_recreated_and_no_line_goes_to_the_deleted_inode(tmp_path):
    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a", "b")
    target.unlink()
    _put(trail, "c", "d")
    assert _ids(target) == ["c", "d"]
    st = trail.status()
    assert st["written"] == 4 and st["ok"] is True and st["reopened"] == 1 and st["lost"] == 0
    trail.close()


def test_a_renamed_file_keeps_its_lines_and_later_lines_go_to_a_new_file(tmp_path):
    target = tmp_path / "trail.jsonl"
    rotated = tmp_path / "trail.jsonl.1"
    trail = AuditTrail(str(target))
    _put(trail, "a", "b")
    os.rename(target, rotated)  # logrotate's default (create): rename, then a new file
    _put(trail, "c")
    os.rename(target, tmp_path / "trail.jsonl.2")
    target.write_text("")  # logrotate's `create` makes the new file itself
    _put(trail, "d", "e")
    trail.close()
    assert _ids(rotated) == ["a", "b"] and _ids(tmp_path / "trail.jsonl.2") == ["c"]
    assert _ids(target) == ["d", "e"] and trail.status()["reopened"] == 2


def test_copytruncate_starts_the_next_lines_at_the_start_of_the_file(tmp_path):
    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a", "b")
    copy = tmp_path / "trail.jsonl.1"
    copy.write_bytes(target.read_bytes())
    os.truncate(target, 0)  # logrotate copytruncate: no hole of NUL bytes before the next line
    _put(trail, "c")
    trail.close()
    assert _ids(copy) == ["a", "b"] and _ids(target) == ["c"]


def test_reopen_closes_and_opens_the_path_again(tmp_path):
    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a")
    trail.reopen()
    _put(trail, "b")
    assert _ids(target) == ["a", "b"] and trail.status()["reopened"] == 1
    trail.close()


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="needs SIGHUP")
def test_sighup_reopens_the_audit_trail(tmp_path):
    from gpnarx.service.app import reload_on_sighup

    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a")
    calls = []

    class Telemetry:
        audit = trail

    class State:
        telemetry = Telemetry()

        async def reload(self):
            calls.append("reload")

    async def main():
        reload_on_sighup(State())
        os.kill(os.getpid(), signal.SIGHUP)
        for _ in range(100):
            await asyncio.sleep(0.01)
            if calls:
                break

    asyncio.run(main())
    assert calls == ["reload"]
    _put(trail, "b")
    assert trail.status()["reopened"] == 1 and _ids(target) == ["a", "b"]
    trail.close()


def _failing_write(monkeypatch, fail_on: set[int], short: bool = False):
    """os.write fails on the calls numbered in ``fail_on`` (1-based from now, for the trail's file): half the bytes are
    written, then ENOSPC is raised (or, ``short``, the half count is returned as a short write)."""
    real = os.write
    n = {"calls": 0}

    def write(fd, data):
        if fd <= 2:
            return real(fd, data)
        n["calls"] += 1
        if n["calls"] in fail_on:
            done = real(fd, bytes(data[: len(data) // 2]))
            if short:
                return done
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data)

    monkeypatch.setattr(audit_mod.os, "write", write)


@pytest.mark.parametrize("short", [False, True], ids=["raises", "short-write"])
def test_a_write_failing_midway_leaves_no_torn_line_and_counts_the_loss(tmp_path, monkeypatch, short):
    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a")
    _failing_write(monkeypatch, {1}, short=short)
    _put(trail, "b")
    _put(trail, "c", "d")
    assert _ids(target) == ["a", "c", "d"]  # every line parses; b is lost, not glued to c
    st = trail.status()
    assert st["written"] == 3 and st["failed"] == 1 and st["lost"] == 1 and st["ok"] is True
    assert "No space left" in st["last_error"] or "short write" in st["last_error"]
    trail.close()


def test_a_fragment_that_cannot_be_removed_is_ended_so_the_next_line_stays_whole(tmp_path, monkeypatch):
    target = tmp_path / "trail.jsonl"
    trail = AuditTrail(str(target))
    _put(trail, "a")
    _failing_write(monkeypatch, {1})

    def no_truncate(fd, length):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(audit_mod.os, "ftruncate", no_truncate)
    _put(trail, "b")
    _put(trail, "c")
    lines = target.read_text().splitlines()
    assert json.loads(lines[0])["request_id"] == "a" and json.loads(lines[-1])["request_id"] == "c"
    assert len(lines) == 3  # the fragment of b stands alone on its line
    st = trail.status()
    assert st["failed"] == 1 and st["torn"] == 1 and st["written"] == 2
    trail.close()


def test_a_file_ending_in_a_fragment_gets_a_newline_before_the_first_line(tmp_path):
    target = tmp_path / "trail.jsonl"
    target.write_text('{"request_id": "old"}\n{"request_id": "cut sh')  # a previous process died mid-line
    trail = AuditTrail(str(target))
    _put(trail, "a")
    trail.close()
    lines = target.read_text().splitlines()
    assert lines[:2] == ['{"request_id": "old"}', '{"request_id": "cut sh'] and len(lines) == 3
    assert json.loads(lines[2])["request_id"] == "a"


def test_losses_and_reopens_are_on_metrics_and_ready(tmp_path, monkeypatch):
    from fastapi.testclient import TestClient
    from test_service_support import built_registry

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    target = tmp_path / "trail.jsonl"
    app = create_app(built_registry().root, Settings(workers=1, queue_size=2, registry_poll=0,
                                                     audit_log=str(target)))
    trail = app.state.service.telemetry.audit
    with TestClient(app) as c:
        _put(trail, "a")
        target.unlink()
        _put(trail, "b")
        _failing_write(monkeypatch, {1})
        _put(trail, "c")
        audit = c.get("/health/ready").json()["audit"]
        assert audit["lost"] == 1 and audit["reopened"] >= 1 and audit["failed"] == 1
        text = c.get("/metrics").text
        assert "gpnarx_audit_lines_lost_total 1.0" in text
        assert 'gpnarx_audit_reopens_total{reason="deleted"} 1.0' in text
    assert _ids(target) == ["b"]
