"""POST /v1/records/parse refuses a record file that declares more than the service's limits from its headers,
before anything is decompressed or allocated (storage.record_formats.check_bounds).

The bombs are built in memory and declare far more than they hold: a deflated .npz member, a .npy header, a
compressed MATLAB v5 variable, a MATLAB cell, an HDF5 dataset of gzip chunks. Each parse is watched with
tracemalloc: its peak must stay far below what the file declares (before the bound, each inflated or allocated
the declared size first, then answered 413 or 422).
"""
from __future__ import annotations

import io
import struct
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest
import scipy.io
from fastapi.testclient import TestClient

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.record_formats import RecordFileError, RecordTooLarge, check_bounds, parse_record

LIMIT = 1000  # GPNARX_MAX_SAMPLES of the app under test [samples]
DECLARED = 50_000_000  # samples the npz, npy and HDF5 bombs declare (400 MB of float64)
PEAK = 50 << 20  # most a refused parse may allocate [bytes]
PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def client():
    return TestClient(create_app(None, Settings(workers=1, queue_size=2, max_samples=LIMIT)),
                      raise_server_exceptions=False)


def _post(client, name, data, fs=None):
    """(response, tracemalloc peak [bytes]) of one parse request."""
    tracemalloc.start()
    try:
        r = client.post("/v1/records/parse", files=[("files", (name, data))],
                        data=None if fs is None else {"fs": str(fs)})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return r, peak


def _problem(r, status):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    p = r.json()
    assert p["status"] == status and p["field"] == "files", p
    return p


def _npy_header(shape, descr="<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _npy(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def npz_bomb(n=DECLARED) -> bytes:
    """u: n float64 zeros, deflated (~0.4 MB for 5e7); fs a scalar."""
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("u.npy", "w", force_zip64=True) as fh:
            fh.write(_npy_header((n,)))
            zeros, left = bytes(8 << 20), n * 8
            while left > 0:
                fh.write(zeros[:min(left, len(zeros))])
                left -= len(zeros)
        zf.writestr("fs.npy", _npy(np.float64(1024.0)))
    return b.getvalue()


def mat_v5(variables, compress=True) -> bytes:
    """A MATLAB v5 file of double row vectors {name: n zeros} written as MATLAB does (one miCOMPRESSED
    element per variable), compressed as a stream so the zeros are never held in memory."""
    out = [b"MATLAB 5.0 MAT-file, test bomb".ljust(116, b" ") + bytes(8) + struct.pack("<H", 0x0100) + b"IM"]
    for name, n in variables.items():
        raw = name.encode()
        pad = raw + bytes(-len(raw) % 8)
        head = (struct.pack("<IIII", 6, 8, 6, 0)  # array flags: mxDOUBLE_CLASS
                + struct.pack("<IIii", 5, 8, 1, n)  # dimensions 1 x n
                + struct.pack("<II", 1, len(raw)) + pad  # name
                + struct.pack("<II", 9, n * 8))  # miDOUBLE data
        payload = len(head) + n * 8
        if not compress:
            out.append(struct.pack("<II", 14, payload) + head + bytes(n * 8))
            continue
        c = zlib.compressobj(1)
        parts = [c.compress(struct.pack("<II", 14, payload) + head)]
        zeros, left = bytes(8 << 20), n * 8
        while left > 0:
            parts.append(c.compress(zeros[:min(left, len(zeros))]))
            left -= len(zeros)
        parts.append(c.flush())
        z = b"".join(parts)
        out.append(struct.pack("<II", 15, len(z)) + z)
    return b"".join(out)


# ------------------------------------------------------------------------------------------ 413 from the headers
def test_npz_bomb_is_refused_from_the_zip_directory_and_header(client):
    data = npz_bomb()
    assert len(data) < 4 << 20
    r, peak = _post(client, "bomb.npz", data)
    p = _problem(r, 413)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    assert p["limit"] == LIMIT
    assert f"u holds {DECLARED} samples" in p["detail"] and "GPNARX_MAX_SAMPLES" in p["detail"]


def test_npy_header_bomb_is_refused_before_numpy_allocates(client):
    data = _npy_header((DECLARED,)) + bytes(800)  # numpy allocates the declared 400 MB before reading
    r, peak = _post(client, "bomb.npy", data, fs=100.0)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    p = _problem(r, 413)
    assert p["limit"] == LIMIT and f"holds {DECLARED} samples" in p["detail"]


def test_compressed_mat_bomb_is_refused_from_the_variable_header(client):
    n = 10_000_000  # 80 MB of zeros in ~80 kB
    data = mat_v5({"u": n})
    assert len(data) < 1 << 20
    r, peak = _post(client, "bomb.mat", data, fs=100.0)
    p = _problem(r, 413)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    assert p["limit"] == LIMIT and f"u holds {n} samples" in p["detail"]


def test_compressed_mat_variable_other_than_u_counts_against_the_body_limit(client):
    # a small u, and a 80 MB compressed variable the parser would inflate with it (scipy loads every variable)
    data = mat_v5({"u": 10, "x": 10_000_000})
    r, peak = _post(client, "bomb.mat", data, fs=100.0)
    p = _problem(r, 413)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    limit = Settings().max_body_bytes
    assert p["limit"] == limit and "variable 'x'" in p["detail"] and "GPNARX_MAX_BODY_BYTES" in p["detail"]


def test_hdf5_compressed_dataset_is_refused_from_its_shape(client):
    h5py = pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        ds = f.create_dataset("u", shape=(DECLARED,), dtype="f8", chunks=(1 << 16,), compression="gzip")
        ds[: 1 << 16] = 0.0  # one written chunk; the others read as the fill value
        f.create_dataset("fs", data=100.0)
    data = buf.getvalue()
    assert len(data) < 4 << 20
    r, peak = _post(client, "bomb.h5", data)
    p = _problem(r, 413)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    assert p["limit"] == LIMIT and f"u holds {DECLARED} samples" in p["detail"]


# ------------------------------------------------------------------------------------------ 422: declared != held
def test_npz_member_whose_header_disagrees_with_the_zip_directory_is_a_422(client):
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("u.npy", _npy_header((10,)) + np.arange(100.0).tobytes())  # header: 10, member: 100 values
        zf.writestr("fs.npy", _npy(np.float64(100.0)))
    r, _ = _post(client, "odd.npz", b.getvalue())
    p = _problem(r, 422)
    assert "corrupt array 'u'" in p["detail"] and "zip directory" in p["detail"]


def test_mat_cell_declaring_more_elements_than_it_holds_is_a_422(client):
    # scipy allocates a cell's element array from its declared dimensions before reading one element
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"u": np.arange(10.0), "fs": 10.0, "c": np.array([np.zeros(1)], dtype=object)})
    data = bytearray(buf.getvalue())
    at = data.index(struct.pack("<IIII", 6, 8, 1, 0))  # the cell's array flags (mxCELL_CLASS)
    struct.pack_into("<ii", data, at + 24, 1, 20_000_000)  # its dimensions: 1 x 2e7 (160 MB of pointers)
    r, peak = _post(client, "cell.mat", bytes(data))
    p = _problem(r, 422)
    assert peak < PEAK, f"peak {peak / 1e6:.0f} MB"
    assert "declares 20000000 elements" in p["detail"]


# ------------------------------------------------------------------------------------------ what still parses
def test_small_npz_and_mat_still_parse(client):
    u = np.sin(np.arange(500) / 7.0)
    npz = io.BytesIO()
    np.savez_compressed(npz, u=u, y=2 * u, fs=100.0, units_u="N", units_y="m", name="run")
    r, _ = _post(client, "r.npz", npz.getvalue())
    assert r.status_code == 200, r.text
    assert r.json()["n_samples"] == 500 and r.json()["units"] == {"u": "N", "y": "m"}
    for compress in (False, True):
        mat = io.BytesIO()
        scipy.io.savemat(mat, {"u": u, "y": 2 * u, "fs": 100.0, "units_u": "N",
                               "meta": {"a": np.arange(3), "b": np.array(["x", np.zeros(2)], dtype=object)}},
                         do_compression=compress)
        r, _ = _post(client, "r.mat", mat.getvalue())
        assert r.status_code == 200, r.text
        np.testing.assert_array_equal(r.json()["y"], 2 * u)
    r, _ = _post(client, "r.mat", mat_v5({"u": 400}), fs=100.0)  # the test builder writes what scipy reads
    assert r.status_code == 200, r.text
    assert r.json()["n_samples"] == 400


def test_parse_record_and_check_bounds_take_the_limits():
    with pytest.raises(RecordTooLarge) as ei:
        parse_record(npz_bomb(10_000), "b.npz", max_samples=LIMIT)
    assert (ei.value.what, ei.value.size, ei.value.limit, ei.value.unit) == ("u", 10_000, LIMIT, "samples")
    with pytest.raises(RecordTooLarge) as ei:
        check_bounds(mat_v5({"u": 10, "x": 10_000}), "b.mat", max_samples=LIMIT, max_bytes=50_000)
    assert ei.value.unit == "bytes" and ei.value.limit == 50_000
    uncompressed = mat_v5({"u": 10, "x": 10_000}, compress=False)  # the upload's size bounds it
    check_bounds(uncompressed, "b.mat", max_samples=LIMIT, max_bytes=50_000)
    with pytest.raises(RecordFileError, match="truncated .npy"):
        check_bounds(_npy_header((500,)) + bytes(80), "t.npy", max_samples=LIMIT)
    assert parse_record(npz_bomb(500), "ok.npz", max_samples=LIMIT, max_bytes=1 << 20).n == 500


def test_hdf5_data_outside_the_file_is_refused(tmp_path):
    """An external link, a dataset in external raw files or a virtual dataset would make the parser read other
    files of the machine that parses an upload: each is refused, naming the dataset."""
    h5py = pytest.importorskip("h5py", reason="h5py (extra `formats`) is not installed")
    from gpnarx.storage.record_formats import RecordFileError, parse_record

    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(64, dtype="<f8").tobytes())
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["u"] = np.ones(64)
    cases = {}
    p = tmp_path / "link.h5"
    with h5py.File(p, "w") as f:
        f["u"] = h5py.ExternalLink(str(other), "/u")
    cases["external link"] = p
    p = tmp_path / "raw.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("u", shape=(64,), dtype="<f8", external=[(str(secret), 0, 64 * 8)])
        f["fs"] = 1024.0
    cases["external storage"] = p
    p = tmp_path / "virtual.h5"
    layout = h5py.VirtualLayout(shape=(64,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(other), "u", shape=(64,))
    with h5py.File(p, "w") as f:
        f.create_virtual_dataset("u", layout)
        f["fs"] = 1024.0
    cases["virtual"] = p
    for what, path in cases.items():
        with pytest.raises(RecordFileError, match="outside the file|external link") as info:
            parse_record(path.read_bytes(), path.name, fs=1024.0)
        assert "'u'" in str(info.value), (what, str(info.value))
    ok = tmp_path / "ok.h5"
    with h5py.File(ok, "w") as f:
        f["u"] = np.ones(64)
        f["fs"] = 1024.0
    assert parse_record(ok.read_bytes(), ok.name).u.size == 64
