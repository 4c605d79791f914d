"""Decompression bombs: small inputs that declare a huge decoded size, one builder per container the service
or the CLI decodes (tests/test_bombs.py, tests/test_parse_bounds.py and bench/bench_bombs.py use them).

Each builder streams its zeros through the compressor, so building a bomb never holds what it declares.
"""
from __future__ import annotations

import base64
import gzip
import hashlib
import hmac
import io
import json
import struct
import zipfile
import zlib

import numpy as np

from gpnarx.operations.stream_token import MAGIC, PUBLIC_KEY

_ZEROS = bytes(8 << 20)


def _stream_zeros(write, n: int) -> None:
    """write(n zero bytes), 8 MiB at a time."""
    while n > 0:
        write(_ZEROS[:min(n, len(_ZEROS))])
        n -= len(_ZEROS)


def npy_header(shape, descr="<f8") -> bytes:
    """The .npy header of an array of ``shape`` and dtype ``descr`` (version 1.0)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(arr))
    return buf.getvalue()


def zip_with_bomb(small: dict, name: str, shape, descr="<f8") -> bytes:
    """A zip archive (an .npz) of the .npy members ``small`` {name: array} and one deflated member ``name`` of
    zeros that declares ``shape`` x ``descr``."""
    itemsize = np.dtype(descr).itemsize
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for k, v in small.items():
            zf.writestr(f"{k}.npy", npy_bytes(v))
        with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
            fh.write(npy_header(shape, descr))
            _stream_zeros(fh.write, int(np.prod(shape, dtype=np.int64)) * itemsize)
    return b.getvalue()


def zip_directory_bomb(n: int = 200_000, declared: int | None = 1) -> bytes:
    """A zip archive that is only a central directory of ``n`` entries (47 bytes each; no member data): ``zipfile``
    makes an object of each (about 400 bytes). Its end record declares ``declared`` entries (None: ``n``)."""
    entry = struct.pack("<4s4B4HL2L5H2L", b"PK\x01\x02", 20, 3, 20, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0)
    directory = (entry + b"x") * n  # stored, empty, named "x"
    count = n if declared is None else declared
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, min(count, 0xFFFF), min(count, 0xFFFF), len(directory), 0, 0)
    return directory + end


# ------------------------------------------------------------------------------------------------ stream tokens
def sign(body: bytes, key: bytes = PUBLIC_KEY) -> str:
    """A stream token of ``body`` (the zlib-compressed NPZ), signed as any client can when no GPNARX_STREAM_KEY
    is set."""
    return base64.urlsafe_b64encode(MAGIC + hmac.new(key, body, hashlib.sha256).digest() + body).decode()


def token_header(model: str, version: str, **extra) -> dict:
    return {"model": model, "version": str(version), "method": "mc", "position": 0, "floor": 0, "retry_in": 0,
            "rng": None, "check_rng": None, **extra}


def token_bomb(model: str, version: str, declared: int = 128 << 20, member: str = "paths",
               descr: str = "|u1") -> str:
    """A token whose NPZ member ``member`` declares ``declared`` bytes of ``descr`` zeros (a 128 MiB uint8
    member: about 1,300 characters; a decoder that casts it to float64 allocates 8 times that)."""
    header = token_header(model, version)
    itemsize = np.dtype(descr).itemsize
    inner = zip_with_bomb({"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8),
                           "u_tail": np.zeros(16)}, member, (declared // itemsize,), descr)
    return sign(zlib.compress(inner, 9))


def token_of(header: dict | str, arrays: dict) -> str:
    """A token holding ``header`` (a dict, or its JSON text) and ``arrays`` as ``operations.stream_token.encode_state``
    writes them."""
    text = header if isinstance(header, str) else json.dumps(header)
    buf = io.BytesIO()
    np.savez(buf, header=np.frombuffer(text.encode(), dtype=np.uint8), **arrays)
    return sign(zlib.compress(buf.getvalue()))


def nested(depth: int, leaf: str = '"1"') -> str:
    """JSON text of ``leaf`` inside ``depth`` objects {"s": {"s": ...}} (written, not dumped: deeper than
    ``json.dumps`` recurses)."""
    return '{"s": ' * depth + leaf + "}" * depth


def with_value(header: dict, key: str, json_text: str) -> str:
    """JSON text of ``header`` with ``header[key]`` replaced by ``json_text``."""
    return json.dumps({**header, key: "@@"}).replace('"@@"', json_text)


def deep_rng_token(model: str, version: str, depth: int = 700) -> str:
    """A token whose ``rng`` nests ``depth`` objects deep (a decoder that recurses over it overflows the stack)."""
    return token_of(with_value(token_header(model, version), "rng", nested(depth)), {"u_tail": np.zeros(16)})


def outer_zlib_bomb(model: str, version: str, declared: int = 512 << 20) -> str:
    """A token whose zlib body itself inflates to ``declared`` bytes (zeros after a short archive)."""
    c = zlib.compressobj(9)
    parts = [c.compress(npy_bytes(np.zeros(4)))]
    _stream_zeros(lambda b: parts.append(c.compress(b)), declared)
    parts.append(c.flush())
    return sign(b"".join(parts))


# ------------------------------------------------------------------------------------------------ HDF5 / MAT v7.3
def hdf5_chunk_bomb(n: int = 10, chunk: int = 1 << 26, mat73: bool = False) -> bytes:
    """An HDF5 file whose dataset ``u`` holds ``n`` samples stored in one gzip chunk of ``chunk`` float64 values
    (512 MiB by default; the file is about 0.5 MB). ``mat73``: laid out as MATLAB -v7.3 saves (a 512-byte
    user block starting with the MAT-file text header)."""
    import h5py

    buf = io.BytesIO()
    with h5py.File(buf, "w", userblock_size=512 if mat73 else 0) as f:
        ds = f.create_dataset("u", shape=(n,), maxshape=(None,), dtype="f8", chunks=(chunk,), compression="gzip")
        ds[:] = np.arange(float(n))
        f.create_dataset("fs", data=100.0)
    return _mat73_text(buf.getvalue()) if mat73 else buf.getvalue()


def hdf5_stream_bomb(n: int = 10, inflated: int = 512 << 20, mat73: bool = False) -> bytes:
    """An HDF5 file whose dataset ``u`` of ``n`` samples is one gzip chunk of ``n`` values whose stored stream
    inflates to ``inflated`` bytes (HDF5's deflate filter inflates it all before it cuts it to the chunk)."""
    import h5py

    c = zlib.compressobj(9)
    parts = []
    _stream_zeros(lambda b: parts.append(c.compress(b)), inflated)
    parts.append(c.flush())
    buf = io.BytesIO()
    with h5py.File(buf, "w", userblock_size=512 if mat73 else 0) as f:
        ds = f.create_dataset("u", shape=(n,), dtype="f8", chunks=(n,), compression="gzip")
        ds.id.write_direct_chunk((0,), b"".join(parts))
        f.create_dataset("fs", data=100.0)
    return _mat73_text(buf.getvalue()) if mat73 else buf.getvalue()


def _mat73_text(data: bytes) -> bytes:
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test bomb HDF5 schema 1.00 .".ljust(116, b" ")
    return head + bytes(8) + struct.pack("<H", 0x0200) + b"IM" + data[128:]


# ------------------------------------------------------------------------------------------------ other bodies
def gzip_bomb(payload_prefix: bytes, declared: int = 256 << 20) -> bytes:
    """gzip of ``payload_prefix`` followed by ``declared`` zero bytes (a Content-Encoding: gzip body)."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", compresslevel=9) as g:
        g.write(payload_prefix)
        _stream_zeros(g.write, declared)
    return out.getvalue()
