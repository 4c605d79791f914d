"""Artefacts built once per test session and shared by every pytest-xdist worker.

A costly fixture artefact (a trained bundle, a registry) is built into a folder of the session's cache
root by whichever worker asks first, under a file lock (``filelock``); the other workers wait on that
lock and then read the finished folder. The folder's name carries a digest of what determines the
artefact (the package's source, the files the builder reads, the builder's own module), so a change to
any of them builds a new one. The root is ``session-cache`` beside the workers' base temporary folders
(``tmp_path_factory.getbasetemp().parent`` under xdist, the session's base folder without it), set by
``tests/conftest.py`` before the first test; outside pytest a private temporary folder is used.
"""
from __future__ import annotations

import atexit
import hashlib
import importlib.util
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

#: the packages of the wheel (pyproject [tool.setuptools] packages): their source decides what is built
PACKAGES = ("gpnarx", "gpnarx.model", "gpnarx.storage", "gpnarx.service", "gpnarx.training", "gpnarx.cli",
            "gpnarx.client", "gpnarx.configs")
DONE = ".complete"  # written last into a finished artefact folder

_root: Path | None = None


def set_root(path: Path) -> None:
    """Use ``path`` (created if missing) as this process's cache root."""
    global _root
    _root = Path(path)
    _root.mkdir(parents=True, exist_ok=True)


def root() -> Path:
    """The cache root: the session's (``set_root``), else a private temporary folder removed at exit."""
    if _root is None:
        tmp = Path(tempfile.mkdtemp(prefix="gpnarx-test-cache-"))
        atexit.register(shutil.rmtree, tmp, True)
        set_root(tmp)
    return _root


def package_files() -> list[Path]:
    """Every .py and .toml file of the installed gpnarx packages (sorted, no duplicates)."""
    files = set()
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        for loc in (spec.submodule_search_locations or []) if spec else []:
            files.update(p.resolve() for p in Path(loc).rglob("*") if p.suffix in (".py", ".toml") and p.is_file())
    return sorted(files)


def digest(*files: Path, extra: str = "") -> str:
    """sha256 (hex) over the package's source, the contents of ``files`` and ``extra``."""
    h = hashlib.sha256(extra.encode())
    for group in (package_files(), [Path(f).resolve() for f in files]):
        for p in group:
            h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def build_once(name: str, key: str, build: Callable[[Path], None], timeout: float = 3600.0) -> Path:
    """The finished folder ``ROOT/NAME-KEY``, built by ``build(folder)`` if no process of the session has.

    ``build`` fills an empty folder; it runs under the lock, at most once per key while it succeeds (a
    failed build leaves nothing behind, and the next caller tries again). ``timeout`` [s]: the longest
    wait for another process's build.
    """
    from filelock import FileLock

    dest = root() / f"{name}-{key[:16]}"
    with FileLock(str(dest) + ".lock", timeout=timeout):
        if not (dest / DONE).is_file():
            part = dest.with_name(dest.name + ".partial")
            shutil.rmtree(part, ignore_errors=True)
            shutil.rmtree(dest, ignore_errors=True)
            part.mkdir()
            try:
                build(part)
                (part / DONE).write_text(key)
            except BaseException:
                shutil.rmtree(part, ignore_errors=True)
                raise
            part.rename(dest)
    return dest
