"""Bundle folders get the permissions of a plain ``mkdir`` and an unreadable bundle is refused, not fatal.

``tempfile.mkdtemp`` makes 0700 folders: a bundle published by renaming one was private to its writer, so
a server running as another user (the image's uid on a mounted registry) could not read it. Every folder
of a written bundle is now 0777 & ~umask and every file 0666 & ~umask. A bundle a server cannot read
(another user's private folder) is refused with a message naming it, as a bad checksum is: the server
starts and serves the rest, and ``POST /v1/admin/reload`` answers with the refusal, never a 500.

The tests run as root too (root reads every folder whatever its mode), so reading a folder is made to fail
with EACCES by patching the ``os`` calls for paths under it, as the kernel answers another user's process.
"""
from __future__ import annotations

import builtins
import errno
import io
import os
import shutil
import stat
from contextlib import contextmanager
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from test_service_support import built_registry

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.bundle import derive_bundle, load_bundle, save_bundle
from gpnarx.storage.registry import Registry


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def _modes(folder: Path) -> tuple[set, set]:
    dirs, files = {_mode(folder)}, set()
    for p in folder.rglob("*"):
        (dirs if p.is_dir() else files).add(_mode(p))
    return dirs, files


@contextmanager
def _umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def _save(reg: Path, name: str, version: str, report: Path | None = None) -> Path:
    b = load_bundle(built_registry().root / "boucwen" / "1")
    m = b.manifest
    return save_bundle(b.model, reg, name, version, fs=m["fs"], units=m["units"], physics=m["physics"],
                       novelty=m["novelty"], training=m["training"], attach_dir=report)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o002])
def test_a_written_bundle_has_the_modes_of_mkdir_and_open(tmp_path, mask):
    report = tmp_path / "private-report"
    report.mkdir(mode=0o700)  # a report built in a TemporaryDirectory is 0700: copytree kept that
    (report / "index.html").write_text("<p>report</p>")
    os.chmod(report / "index.html", 0o600)
    with _umask(mask):
        folder = _save(tmp_path / "reg", "perm", "1", report)
        derived = derive_bundle(load_bundle(folder), tmp_path / "reg", {"training": {"note": "derived"}})
    for f in (folder, derived):
        dirs, files = _modes(f)
        assert dirs == {0o777 & ~mask}, (oct(mask), [oct(d) for d in dirs])
        assert files == {0o666 & ~mask}, (oct(mask), [oct(x) for x in files])


# -------------------------------------------------------------------------------- another user's bundle
@contextmanager
def _unreadable(*folders: Path):
    """Reading inside ``folders`` fails with EACCES (listing them, stat or open of what they hold)."""
    roots = [str(f) for f in folders]

    def inside(path) -> bool:
        try:
            p = os.fsdecode(os.fspath(path))
        except TypeError:
            return False
        p = os.path.abspath(p)
        return any(p.startswith(r + os.sep) for r in roots)

    def listing(path) -> bool:
        try:
            return os.path.abspath(os.fsdecode(os.fspath(path))) in roots or inside(path)
        except TypeError:
            return False

    def denied(path):
        return PermissionError(errno.EACCES, "Permission denied", os.fsdecode(os.fspath(path)))

    real = {"stat": os.stat, "listdir": os.listdir, "scandir": os.scandir, "open": builtins.open,
            "io_open": io.open, "os_open": os.open}

    def p_stat(path, *a, **k):
        if not isinstance(path, int) and inside(path):
            raise denied(path)
        return real["stat"](path, *a, **k)

    def p_listdir(path=".", *a, **k):
        if listing(path):
            raise denied(path)
        return real["listdir"](path, *a, **k)

    def p_scandir(path=".", *a, **k):
        if not isinstance(path, int) and listing(path):
            raise denied(path)
        return real["scandir"](path, *a, **k)

    def p_open(file, *a, **k):
        if not isinstance(file, int) and inside(file):
            raise denied(file)
        return real["open"](file, *a, **k)

    def p_os_open(path, *a, **k):
        if inside(path):
            raise denied(path)
        return real["os_open"](path, *a, **k)

    mp = pytest.MonkeyPatch()
    mp.setattr(os, "stat", p_stat)
    mp.setattr(os, "listdir", p_listdir)
    mp.setattr(os, "scandir", p_scandir)
    mp.setattr(os, "open", p_os_open)
    mp.setattr(builtins, "open", p_open)
    mp.setattr(io, "open", p_open)
    try:
        yield
    finally:
        mp.undo()


def _registry(tmp_path) -> Path:
    reg = tmp_path / "reg"
    shutil.copytree(built_registry().root, reg)
    return reg


def test_the_server_starts_and_serves_the_rest_when_one_bundle_is_unreadable(tmp_path):
    reg = _registry(tmp_path)
    with _unreadable(reg / "boucwen" / "1", reg / "plain"):  # a version folder and a whole model folder
        app = create_app(reg, Settings(workers=1, queue_size=2, registry_poll=0))
        with TestClient(app) as c:
            ready = c.get("/health/ready")
            assert ready.status_code == 200, ready.text
            body = ready.json()
            assert body["models"] == {"boucwen": ["2"]}
            reasons = {r["path"]: r["reason"] for r in body["refused"]}
            assert set(reasons) == {"boucwen/1", "plain"}, reasons
            for reason in reasons.values():
                assert "Permission denied" in reason and "readable" in reason, reason
            assert c.get("/v1/models/boucwen").status_code == 200
            r = c.get("/v1/models/boucwen/versions/1")
            assert r.status_code == 404 and "Permission denied" in r.json()["detail"]


def test_reload_with_a_new_unreadable_version_answers_the_refusal_not_500(tmp_path):
    reg = _registry(tmp_path)
    app = create_app(reg, Settings(workers=1, queue_size=2, registry_poll=0))
    with TestClient(app, raise_server_exceptions=False) as c:
        shutil.copytree(reg / "boucwen" / "2", reg / "boucwen" / "3")  # appears while the server runs
        with _unreadable(reg / "boucwen" / "3"):
            r = c.post("/v1/admin/reload")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["refused"][0]["path"] == "boucwen/3" and "Permission denied" in body["refused"][0]["reason"]
        assert body["models"]["boucwen"] == ["1", "2"]
        assert c.get("/health/ready").status_code == 200


def test_a_bundle_unreadable_when_first_built_is_refused_not_500(tmp_path):
    reg = _registry(tmp_path)
    registry = Registry(reg, lazy=True).scan()  # verified while readable; built on first use
    with _unreadable(reg / "plain" / "1"):
        with pytest.raises(KeyError, match="Permission denied"):
            registry.get("plain", "1")
    assert "plain" not in registry.names() and registry.refused[0]["path"].endswith("plain/1")
