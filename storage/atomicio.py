"""Atomic local file writes: the one helper every writer of the package uses.

The data go to a temporary file in the destination's folder (same filesystem), are flushed and
fsynced, and the file then replaces the destination with ``os.replace``: a reader sees the old
file or the new one, never half of one, and a failed write leaves no temporary file behind. The file
gets the mode a plain ``open()`` would give it (0666 less the umask: 0644 under the usual 022), not
the temporary file's private 0600.
(Bundles are folders: ``storage.bundle`` publishes them by renaming a temporary folder, given the modes of a
plain ``mkdir`` and ``open()`` first by ``plain_modes``.)
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


def _umask() -> int:
    """The process's umask, read without changing it where Linux says it (/proc), else by setting it back."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the umask."""
    return 0o666 & ~_umask()


def dir_mode() -> int:
    """The mode ``mkdir`` gives a new folder: 0777 less the umask."""
    return 0o777 & ~_umask()


def plain_modes(folder) -> None:
    """Give ``folder`` and every folder and file under it the modes ``mkdir`` and ``open()`` would give them
    (``dir_mode``, ``file_mode``), as after ``tempfile.mkdtemp`` (0700) or a copy of private files; links are
    left as they are."""
    folder = Path(os.fspath(folder))
    dmode, fmode = dir_mode(), file_mode()
    os.chmod(folder, dmode)
    for here, dirs, files in os.walk(folder):
        for d in dirs:
            p = os.path.join(here, d)
            if not os.path.islink(p):
                os.chmod(p, dmode)
        for f in files:
            p = os.path.join(here, f)
            if not os.path.islink(p):
                os.chmod(p, fmode)


@contextmanager
def atomic_file(path, mode: str = "wb", *, encoding: str | None = None) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing (``mode`` 'wb' or 'w'); when the block
    ends without an error it replaces ``path``, otherwise it is removed."""
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(os.fspath(path))
    parent = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent)
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, file_mode())  # mkstemp's 0600 would make a record or report private to its writer
        with os.fdopen(fd, mode, **({"encoding": encoding or "utf-8"} if mode == "w" else {})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_atomic(path, data: bytes | str) -> None:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` atomically (see the module docstring)."""
    with atomic_file(path, "w" if isinstance(data, str) else "wb") as f:
        f.write(data)


__all__ = ["atomic_file", "dir_mode", "file_mode", "plain_modes", "write_atomic"]
