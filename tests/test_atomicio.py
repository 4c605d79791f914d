"""The one atomic-write helper (gpnarx.storage.atomicio)."""
from __future__ import annotations

import numpy as np
import pytest

from gpnarx.storage.atomicio import atomic_file, write_atomic


def test_write_atomic_text_and_bytes(tmp_path):
    p = tmp_path / "a.json"
    write_atomic(p, '{"x": 1}')
    assert p.read_text() == '{"x": 1}'
    write_atomic(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"
    assert [q.name for q in tmp_path.iterdir()] == ["a.json"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "r.npz"
    write_atomic(p, b"old")
    with pytest.raises(RuntimeError):
        with atomic_file(p) as f:
            np.savez(f, u=np.arange(3.0))
            raise RuntimeError("disk full")
    assert p.read_bytes() == b"old"
    assert [q.name for q in tmp_path.iterdir()] == ["r.npz"]
    with atomic_file(p) as f:
        np.savez(f, u=np.arange(3.0))
    assert np.load(p)["u"].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(ValueError, match="mode"):
        with atomic_file(p, "a"):
            pass


def test_files_get_the_mode_open_would_give_not_mkstemps_0600(tmp_path):
    """A record written by `gpnarx simulate` (or any atomic write) is readable by the group and others
    under the usual umask 022, as a plain open() would make it; a stricter umask is respected."""
    import os
    import stat

    from gpnarx.cli.main import main

    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "a.txt", "x")
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
        out = tmp_path / "rec.npz"
        assert main(["simulate", "bouc-wen", "--excitation", "sine", "--freq", "35", "--amplitude", "10",
                     "--duration", "0.2", "--out", str(out)]) == 0
        assert stat.S_IMODE(out.stat().st_mode) == 0o644
        os.umask(0o077)
        write_atomic(tmp_path / "b.txt", "x")
        assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o600
    finally:
        os.umask(old)
