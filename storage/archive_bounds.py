"""Zip archives of .npy arrays (.npz) from untrusted bytes: every size decided before anything is inflated.

``numpy.load`` inflates a member and allocates the array its header declares before a caller can check
either, and ``zipfile`` builds an object per entry of the central directory before a caller can count them.
Here the entry count is read from the end-of-central-directory record first (:func:`open_archive`), and each
member's size from the zip directory (its declared uncompressed size) and its .npy header (shape and dtype)
(:func:`member`): the two must agree, so a caller that bounds the declared sizes bounds what is inflated
(``zipfile`` never inflates a member past its declared size) and what is allocated (:func:`read`).

Used by the stream token (``operations.stream_token``) and, through ``storage.record_formats``, the record
uploads and the NPZ request bodies of the service (``service.wire``).
"""
from __future__ import annotations

import io
import lzma
import math
import struct
import tokenize
import zipfile
import zlib
from dataclasses import dataclass

import numpy as np

#: largest .npy header read [bytes] (numpy's own default: what np.load reads)
NPY_HEADER_MAX = 10000

#: what reading a damaged .npy member of a zip archive can raise: the zip layer (a bad CRC, an unknown or encrypted
#: method, a damaged deflate, bzip2 or LZMA stream) and numpy's .npy header parser (its tokenizer and literal
#: evaluation)
NPY_READ_ERRORS = (ValueError, EOFError, OSError, zipfile.BadZipFile, NotImplementedError, RuntimeError, zlib.error,
                   lzma.LZMAError, tokenize.TokenError, SyntaxError, RecursionError, TypeError, KeyError)

_EOCD = struct.Struct("<4s4H2LH")  # end of central directory: signature, disks, entries here, entries, sizes, comment
_EOCD_SIG = b"PK\x05\x06"


class ArchiveError(ValueError):
    """An archive or one of its members that cannot be read within its bounds: ``member`` (the array's name, or
    None for the archive), ``size`` and ``limit`` (when a bound was exceeded)."""

    def __init__(self, detail: str, member: str | None = None, size: int | None = None, limit: int | None = None):
        super().__init__(detail)
        self.member, self.size, self.limit = member, size, limit


def npy_header(fh, max_header_size: int = NPY_HEADER_MAX):
    """(shape, dtype) of the .npy array at ``fh``'s position, read from its header only (at most
    ``max_header_size`` bytes); ``fh`` is left at the start of its data. None when ``fh`` does not start with the
    .npy magic (np.load then reads the member as raw bytes). Raises one of ``NPY_READ_ERRORS`` on a damaged
    header."""
    fmt = np.lib.format
    magic = fh.read(fmt.MAGIC_LEN)
    if magic[:len(fmt.MAGIC_PREFIX)] != fmt.MAGIC_PREFIX:
        return None
    version = tuple(magic[len(fmt.MAGIC_PREFIX):])
    if version not in ((1, 0), (2, 0), (3, 0)):
        raise ValueError(f"unsupported .npy version {version}")
    reader = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, _, dtype = reader(fh, max_header_size=max_header_size)
    return shape, dtype


#: most bytes of central directory per member an archive may have (a member written by numpy takes about 100)
DIRECTORY_BYTES_PER_MEMBER = 1024


def declared_directory(fh) -> tuple[int, int] | None:
    """(entries, bytes) of the central directory of the zip archive in the seekable binary file ``fh``, as its
    end-of-central-directory record declares them; None when there is no such record (not a zip archive, left to
    ``zipfile`` to refuse). A Zip64 archive declares 0xFFFF entries and 0xFFFFFFFF bytes there."""
    end = fh.seek(0, 2)
    fh.seek(max(0, end - _EOCD.size - 0xFFFF))
    tail = fh.read()
    at = tail.rfind(_EOCD_SIG)
    if at < 0 or at + _EOCD.size > len(tail):
        return None
    fields = _EOCD.unpack_from(tail, at)
    return fields[4], fields[5]


def open_archive(data, max_members: int) -> zipfile.ZipFile:
    """``data`` (bytes or a seekable binary file) as a ``zipfile.ZipFile``, once its directory is known to hold at
    most ``max_members`` entries.

    ``zipfile`` makes an object of every entry in the directory's declared byte size (whatever the entry count
    says), so both are checked first: at most ``max_members`` entries in at most ``DIRECTORY_BYTES_PER_MEMBER``
    bytes each (``ArchiveError`` with ``limit``: the members). Raises one of ``NPY_READ_ERRORS`` when it is not
    a readable zip archive."""
    fh = io.BytesIO(data) if isinstance(data, (bytes, bytearray, memoryview)) else data
    declared = declared_directory(fh)
    fh.seek(0)
    if declared is not None:
        entries, size = declared
        if entries > max_members:
            shown = "65535 or more" if entries == 0xFFFF else str(entries)
            raise ArchiveError(f"the archive declares {shown} members; the limit is {max_members}", size=entries,
                               limit=max_members)
        if size > max_members * DIRECTORY_BYTES_PER_MEMBER:
            raise ArchiveError(f"the archive's directory is {size} bytes, more than {max_members} members take; "
                               f"the limit is {max_members} members", size=entries, limit=max_members)
    zf = zipfile.ZipFile(fh)
    n = len(zf.infolist())
    if n > max_members:  # a directory of more entries than its end record says
        zf.close()
        raise ArchiveError(f"the archive holds {n} members; the limit is {max_members}", size=n, limit=max_members)
    return zf


def member_name(info: zipfile.ZipInfo) -> str:
    """The array name of a member (``np.load``'s: its file name without ``.npy``)."""
    name = info.filename
    return name[:-4] if name.endswith(".npy") else name


@dataclass(frozen=True)
class Member:
    """An .npy member of an archive, as its directory entry and header declare it."""

    name: str
    info: zipfile.ZipInfo
    shape: tuple
    dtype: np.dtype
    header_bytes: int

    @property
    def count(self) -> int:
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        """Data bytes the header declares (= the directory's declared size less the header)."""
        return self.count * self.dtype.itemsize


def member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, max_header_size: int = NPY_HEADER_MAX) -> Member | None:
    """The member ``info`` of ``zf`` as declared, from its first bytes only; None when it is not an .npy array.

    Raises ``ArchiveError`` naming the member when its .npy header and the zip directory disagree on its size
    (reading it would inflate or allocate what one of them declares, not what it holds), and one of
    ``NPY_READ_ERRORS`` when its header is damaged."""
    name = member_name(info)
    with zf.open(info) as fh:
        head = npy_header(fh, max_header_size)
        header_bytes = fh.tell()
    if head is None:
        return None
    shape, dtype = head
    m = Member(name, info, tuple(shape), dtype, header_bytes)
    if not dtype.hasobject and header_bytes + m.nbytes != info.file_size:
        raise ArchiveError(f"corrupt array {name!r}: its .npy header says {m.nbytes} data bytes, the zip directory "
                           f"{info.file_size - header_bytes}", name)
    return m


def read(zf: zipfile.ZipFile, m: Member, max_header_size: int = NPY_HEADER_MAX) -> np.ndarray:
    """The array of the member ``m`` (checked by :func:`member`): inflated and allocated at its declared size."""
    with zf.open(m.info) as fh:
        return np.lib.format.read_array(fh, allow_pickle=False, max_header_size=max_header_size)


__all__ = ["DIRECTORY_BYTES_PER_MEMBER", "NPY_HEADER_MAX", "NPY_READ_ERRORS", "ArchiveError", "Member",
           "declared_directory", "member",
           "member_name", "npy_header", "open_archive", "read"]
