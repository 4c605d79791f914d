"""Bomb fuzz pass: for each container the service decodes, a small input that declares a huge decoded size is
refused fast (413 or 422 naming the field and the limit) and the process's peak RSS grows by less than ``GROWTH``.

Containers: the stream token (``state``: its zlib body, its NPZ members, its JSON header), the NPZ request body,
a gzip-encoded request body, and the record uploads of ``POST /v1/records/parse`` (NPZ, NPY, MATLAB v5, an LMS
export, HDF5 and MATLAB v7.3 chunks, CSV, UFF-58, TDMS). The builders are ``tests/bomb_files.py``; the header
checks of each format are ``tests/test_parse_bounds.py`` (tracemalloc) and ``tests/test_wire_formats.py``: here the
whole process is measured (its ``VmHWM``, reset before each request), which also sees what C libraries (zlib,
HDF5) allocate.
"""
from __future__ import annotations

import io
import struct
import time
import zipfile

import numpy as np
import pytest
from bomb_files import (
    deep_rng_token,
    gzip_bomb,
    hdf5_chunk_bomb,
    hdf5_stream_bomb,
    nested,
    npy_bytes,
    npy_header,
    outer_zlib_bomb,
    token_bomb,
    token_header,
    token_of,
    with_value,
    zip_directory_bomb,
    zip_with_bomb,
)
from fastapi.testclient import TestClient
from test_parse_bounds import mat_v5, npz_bomb
from test_service_support import FS, built_registry, short_record

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

GROWTH = 50 << 20  # most a refused bomb may raise the process's peak RSS [bytes]
FAST = 5.0  # most seconds a refusal may take (a loaded CI machine; the refusals take milliseconds)
LIMIT = 1000  # GPNARX_MAX_SAMPLES of the apps under test
MODEL = "boucwen"


def _kb(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def measured(send):
    """(response, peak RSS growth [bytes], seconds) of ``send()``: the peak (``VmHWM``) is reset first."""
    with open("/proc/self/clear_refs", "w") as fh:  # Linux: 5 resets the peak resident set size
        fh.write("5")
    before = _kb("VmRSS")
    t0 = time.perf_counter()
    r = send()
    took = time.perf_counter() - t0
    return r, _kb("VmHWM") - before, took


def refused(send, status: int, field: str):
    """The problem of a refusal that is fast and light; asserts its status and field."""
    r, grew, took = measured(send)
    assert r.status_code == status, r.text[:400]
    p = r.json()
    assert p["field"] == field, p
    assert grew < GROWTH, f"peak RSS grew by {grew / 2**20:.0f} MiB"
    assert took < FAST, f"took {took:.1f} s"
    return p


@pytest.fixture(scope="module")
def client():
    return TestClient(create_app(built_registry().root, Settings(workers=1, queue_size=4, max_samples=LIMIT)),
                      raise_server_exceptions=False)


@pytest.fixture(scope="module")
def version(client):
    """The version a token names: the model's latest, which the routes without a version use."""
    return client.get(f"/v1/models/{MODEL}").json()["version"]


# ------------------------------------------------------------------------------------------------ stream tokens
def _predict(client, token, **extra):
    u, _ = short_record(200, 3)
    body = {"u": u.tolist(), "fs": FS, "method": "mc", "mc_paths": 16, "seed": 0, "state": token, **extra}
    return client.post(f"/v1/models/{MODEL}/predict", json=body)


def test_token_whose_member_declares_128_mib_is_refused_from_the_zip_directory(client, version):
    token = token_bomb(MODEL, version)  # about 1,300 characters; 1 GiB once cast to float64
    assert len(token) < 2000
    p = refused(lambda: _predict(client, token), 422, "state")
    assert "'paths'" in p["detail"] and str(128 << 20) in p["detail"], p["detail"]
    assert isinstance(p["limit"], int) and p["limit"] < 16 << 20 and str(p["limit"]) in p["detail"]


def test_token_member_bomb_of_float64_and_of_a_carry_array(client, version):
    for member, descr in (("cov", "<f8"), ("carry.loops.extra", "<f8"), ("u_tail", "<f8")):
        token = token_bomb(MODEL, version, 256 << 20, member, descr)
        p = refused(lambda t=token: _predict(client, t), 422, "state")
        assert f"'{member}'" in p["detail"], p["detail"]


def test_token_whose_zlib_body_inflates_to_512_mib_is_refused_while_inflating(client, version):
    p = refused(lambda: _predict(client, outer_zlib_bomb(MODEL, version)), 422, "state")
    assert "inflates" in p["detail"] and str(p["limit"]) in p["detail"], p["detail"]


@pytest.mark.parametrize("depth", [40, 700, 900, 5000])
def test_token_whose_rng_nests_deep_is_a_422_not_a_500(client, version, depth):
    p = refused(lambda: _predict(client, deep_rng_token(MODEL, version, depth)), 422, "state")
    assert "nest" in p["detail"], p["detail"]


def test_token_whose_carry_nests_deep_is_a_422(client, version):
    header = token_header(MODEL, version, method="linear")
    for cuts in (nested(40), "[" * 100_000 + "]" * 100_000):  # the second deeper than json itself parses
        token = token_of(with_value(header, "carry", '{"loops": {"cuts": ' + cuts + "}}"), {"u_tail": np.zeros(16)})
        p = refused(lambda t=token: _predict(client, t, method="linear"), 422, "state")
        assert "nest" in p["detail"], p["detail"]


def test_token_members_of_another_dtype_name_or_count_are_422(client, version):
    cases = {
        "dtype": {"u_tail": np.zeros(16, dtype=np.uint8)},  # a state's arrays are float64
        "name": {"u_tail": np.zeros(16), "junk": np.zeros(3)},
        "count": {"u_tail": np.zeros(16), **{f"carry.x.a{i}": np.zeros(1) for i in range(40)}},
        "shape": {"u_tail": np.zeros((2, 2, 4))},
    }
    for what, arrays in cases.items():
        p = refused(lambda a=arrays: _predict(client, token_of(token_header(MODEL, version), a)), 422, "state")
        assert p["detail"].startswith("state"), (what, p["detail"])


def test_token_member_whose_header_disagrees_with_the_zip_directory_is_a_422(client):
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w") as zf:
        zf.writestr("header.npy", npy_bytes(np.frombuffer(b'{"model": "boucwen"}', dtype=np.uint8)))
        zf.writestr("u_tail.npy", npy_header((1 << 24,)) + bytes(128))  # declares 128 MiB, holds 128 bytes
    import zlib

    from bomb_files import sign

    p = refused(lambda: _predict(client, sign(zlib.compress(b.getvalue()))), 422, "state")
    assert "'u_tail'" in p["detail"], p["detail"]


def test_token_bomb_in_a_batch_is_its_slots_422(client, version):
    u, _ = short_record(200, 3)
    good = {"model": MODEL, "operation": "predict", "u": u.tolist(), "fs": FS, "method": "mc", "mc_paths": 16}
    bad = {**good, "state": token_bomb(MODEL, version)}
    r, grew, took = measured(lambda: client.post("/v1/batch", json={"requests": [good, bad]}))
    assert r.status_code == 200, r.text[:300]
    res = r.json()["results"]
    assert "status" not in res[0] and res[1]["status"] == 422 and res[1]["field"] == "requests.1.state", res[1]
    assert grew < GROWTH and took < FAST


def test_legitimate_tokens_still_continue_the_stream(client):
    """A state of the largest kind a call writes (a Monte Carlo loops carry) is under the limit it is checked
    against: the stream continues."""
    u, _ = short_record(1200, 3)
    body = {"u": u[:600].tolist(), "fs": FS, "method": "mc", "mc_paths": 64, "seed": 0, "return_state": True}
    r = client.post(f"/v1/models/{MODEL}/loops", json=body)
    assert r.status_code == 200, r.text[:300]
    r2 = client.post(f"/v1/models/{MODEL}/loops", json={**body, "u": u[600:].tolist(), "state": r.json()["state"]})
    assert r2.status_code == 200, r2.text[:300]


def test_a_large_token_is_decoded_off_the_event_loop(client, version, monkeypatch):
    """Decoding the largest token a call takes (11.9 MB of arrays at 4096 paths) costs about 0.15 s of CPU: a
    request whose token is at least ``bodies.OFF_LOOP_BYTES`` long is planned (and its token decoded) on a worker
    thread, a short one inline, on a single record route and in a batch."""
    import asyncio

    from gpnarx.service import bodies, ops

    seen, real = [], ops.plan

    def spy(*args, **kw):
        try:
            asyncio.get_running_loop()
            seen.append(True)
        except RuntimeError:
            seen.append(False)
        return real(*args, **kw)

    monkeypatch.setattr(ops, "plan", spy)
    paths = np.random.default_rng(0).normal(size=(1024, 20))
    large = token_of(token_header(MODEL, version), {"u_tail": np.zeros(16), "paths": paths})
    small = token_of(token_header(MODEL, version), {"u_tail": np.zeros(16)})
    assert len(large) >= bodies.OFF_LOOP_BYTES > len(small)
    for token in (small, large):
        assert _predict(client, token).status_code == 422  # 16 paths asked, the token's differ
    u, _ = short_record(200, 3)
    item = {"model": MODEL, "operation": "predict", "u": u.tolist(), "fs": FS, "method": "mc", "mc_paths": 16}
    r = client.post("/v1/batch", json={"requests": [{**item, "state": small}, {**item, "state": large}]})
    assert r.status_code == 200 and [x["status"] for x in r.json()["results"]] == [422, 422], r.text[:300]
    assert seen == [True, False, True, False], seen


# ------------------------------------------------------------------------------------------------ HDF5 / MAT v7.3
def _parse(client, name, data, fs=None):
    return client.post("/v1/records/parse", files=[("files", (name, data))],
                       data=None if fs is None else {"fs": str(fs)})


@pytest.mark.parametrize("name", ["bomb.h5", "bomb.mat"])
def test_hdf5_sample_in_a_512_mib_chunk_is_413_from_the_chunk_layout(client, name):
    pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    data = hdf5_chunk_bomb(mat73=name.endswith(".mat"))
    assert len(data) < 1 << 20
    p = refused(lambda: _parse(client, name, data), 413, "files")
    assert "'u'" in p["detail"] and "chunk" in p["detail"] and str(p["limit"]) in p["detail"], p["detail"]


@pytest.mark.parametrize("name", ["bomb.h5", "bomb.mat"])
def test_hdf5_chunk_whose_stream_inflates_past_its_size_is_a_422(client, name):
    """A chunk of 10 values whose deflate stream holds 512 MiB: HDF5's filter inflates it all before cutting it to
    the chunk. The stream is inflated first, 1 MiB at a time, at most to the chunk's 80 bytes."""
    pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    data = hdf5_stream_bomb(mat73=name.endswith(".mat"))
    assert len(data) < 1 << 20
    p = refused(lambda: _parse(client, name, data), 422, "files")
    assert "dataset 'u'" in p["detail"] and "inflates past the 80 bytes of its chunk" in p["detail"], p["detail"]


def test_hdf5_filters_whose_output_size_is_unchecked_are_a_422(client):
    h5py = pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.create_dataset("u", data=np.zeros(100), chunks=(10,), compression="lzf")
        f.create_dataset("fs", data=100.0)
    p = refused(lambda: _parse(client, "lzf.h5", buf.getvalue()), 422, "files")
    assert "dataset 'u'" in p["detail"] and "lzf" in p["detail"] and "gzip" in p["detail"], p["detail"]


def test_hdf5_and_mat73_records_in_chunks_still_parse(client):
    h5py = pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    u = np.sin(np.arange(900) / 5.0)
    for kw in ({"chunks": (128,), "compression": "gzip", "shuffle": True, "fletcher32": True},
               {"chunks": (100,), "compression": "gzip"}, {"chunks": (64,)}, {}):
        buf = io.BytesIO()
        with h5py.File(buf, "w") as f:
            f.create_dataset("u", data=u, **kw)
            f.create_dataset("y", data=2 * u, **kw)
            f.create_dataset("fs", data=100.0)
        r = _parse(client, "ok.h5", buf.getvalue())
        assert r.status_code == 200, (kw, r.text[:300])
        np.testing.assert_array_equal(r.json()["y"], 2 * u)


# ------------------------------------------------------------------------------------------------ other containers
def _lms_bomb() -> list:
    return [("files", ("Time.mat", mat_v5({"u": 10}))), ("files", ("TimeShaker.mat", mat_v5({"x": 10_000_000})))]


def _tdms(n: int) -> bytes:
    nptdms = pytest.importorskip("nptdms", reason="npTDMS (extra `formats`) is not installed")
    buf = io.BytesIO()
    with nptdms.TdmsWriter(buf) as w:
        w.write_segment([nptdms.ChannelObject("g", "u", np.zeros(n)), nptdms.ChannelObject("g", "y", np.zeros(n))])
    return buf.getvalue()


def _tdms_declaring(n: int) -> bytes:
    """A TDMS file of 10 values whose segment declares ``n`` per channel."""
    data = bytearray(_tdms(10))
    for _ in range(2):  # u, then y
        i = data.index(struct.pack("<IIIQ", 20, 10, 1, 10))
        struct.pack_into("<Q", data, i + 12, n)
    return bytes(data)


def _uff_declaring(n: int) -> bytes:
    pyuff = pytest.importorskip("pyuff", reason="pyuff (extra `formats`) is not installed")
    import os
    import tempfile

    from test_record_formats_extra import uff58

    fd, tmp = tempfile.mkstemp(suffix=".uff")
    os.close(fd)
    os.unlink(tmp)
    try:
        pyuff.UFF(tmp).write_sets(uff58("u", np.arange(10.0), "N"), mode="add")
        lines = open(tmp, "rb").read().split(b"\n")
    finally:
        os.unlink(tmp)
    at = next(i for i, ln in enumerate(lines) if ln.strip() == b"58") + 7  # record 7: num_pts in columns 11-20
    lines[at] = lines[at][:10] + b"%10d" % n + lines[at][20:]
    return b"\n".join(lines)


UPLOADS = {  # name -> (file name, builder, status): each declares far more than it holds or than the limits
    "npz": ("bomb.npz", lambda: npz_bomb(), 413),
    "npz-directory": ("many.npz", lambda: zip_directory_bomb(300_000), 422),  # 13.5 MiB, 300,000 entries
    "npy": ("bomb.npy", lambda: npy_header((50_000_000,)) + bytes(800), 413),
    "mat-v5": ("bomb.mat", lambda: mat_v5({"u": 10_000_000}), 413),
    "csv": ("bomb.csv", lambda: b"u\n" + b"1\n" * (2 << 20), 413),  # 4 MiB of rows: 2,097,152 samples
    "tdms": ("bomb.tdms", lambda: _tdms(LIMIT + 1), 413),
    "uff": ("bomb.uff", lambda: _uff_declaring(100_000_000), 422),
}


@pytest.mark.parametrize("kind", list(UPLOADS))
def test_upload_bombs_are_refused_fast_and_light(client, kind):
    name, build, status = UPLOADS[kind]
    data = build()
    fs = None if kind == "uff" else 100.0  # the UFF file states its own
    p = refused(lambda: _parse(client, name, data, fs=fs), status, "files")
    if status == 413:
        assert p["limit"] and str(p["limit"]) in p["detail"], p["detail"]


def test_lms_export_with_a_compressed_bomb_is_refused(client):
    p = refused(lambda: client.post("/v1/records/parse", files=_lms_bomb()), 413, "files")
    assert "TimeShaker.mat" in p["detail"], p["detail"]


def test_tdms_declaring_more_than_it_holds_reads_what_it_holds(client):
    """npTDMS counts a segment's values from the bytes it holds (an interrupted acquisition's last segment): a
    segment declaring 10^8 values in a 300-byte file is read as its 10 values, never allocated as declared."""
    data = _tdms_declaring(100_000_000)
    r, grew, took = measured(lambda: _parse(client, "short.tdms", data, fs=100.0))
    assert r.status_code == 200 and r.json()["n_samples"] == 10, r.text[:300]
    assert grew < GROWTH and took < FAST


def test_npz_request_body_bomb_is_refused_fast_and_light(client):
    u, _ = short_record(100, 3)
    body = zip_with_bomb({"u": u}, "y", (64 << 20,))  # y: 512 MiB of float64 zeros
    p = refused(lambda: client.post(f"/v1/models/{MODEL}/predict?fs={FS}", content=body,
                                    headers={"content-type": "application/x-npz"}), 413, "y")
    assert str(p["limit"]) in p["detail"], p["detail"]


def test_npz_request_body_directory_bomb_is_refused_fast_and_light(client):
    p = refused(lambda: client.post(f"/v1/models/{MODEL}/predict?fs={FS}", content=zip_directory_bomb(300_000),
                                    headers={"content-type": "application/x-npz"}), 422, "body")
    assert p["limit"] == 8 and "members" in p["detail"], p["detail"]


def test_gzip_request_body_bomb_is_refused_fast_and_light():
    """Decoded up to the body cap (a plain body of that size is read too): under a 1 MiB cap, a gzip body of
    256 MiB of zeros costs what a 1 MiB body costs."""
    client = TestClient(create_app(built_registry().root, Settings(workers=1, queue_size=4, max_body_bytes=1 << 20)),
                        raise_server_exceptions=False)
    u, _ = short_record(100, 3)
    body = gzip_bomb(b'{"fs": 750.0, "u": ' + str(u.tolist()).encode() + b'}')
    p = refused(lambda: client.post(f"/v1/models/{MODEL}/predict", content=body, headers={
        "content-type": "application/json", "content-encoding": "gzip"}), 413, "body")
    assert p["limit"], p
