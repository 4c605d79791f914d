"""Wire formats beyond JSON: NPZ request bodies and answers, ETags and conditional GETs (and the gzip
settings of answers, applied by ``service.app``).

NPZ request bodies (``content-type: application/x-npz``, or ``application/octet-stream``: the generic binary
type, which the OpenAPI document names so that client generators understand it) on the record routes (predict,
loops, novelty): the archive holds the arrays ``u``, ``y``, ``y0`` (1-D, integer or floating point) and
optionally the scalar ``fs`` [Hz], and may hold the metadata of the package's own record files
(``storage.record_files.write_record``, what ``gpnarx simulate --out FILE.npz`` writes): ``units_u`` and
``units_y`` (unit labels, checked against the model's units: ``check_units``) and ``name`` (ignored), each a
short unicode string; every other field of the JSON body (``mc_paths``, ``seed``,
``confidence``, ``method``, ``backend``, ``start``, and ``fs`` when the archive has none) is a query
parameter. The archive is hostile input: it is read without pickle, at most ``MAX_MEMBERS``
members, each array's size is checked from the archive directory and the ``.npy`` header *before*
anything is decompressed or allocated, and the decompressed total is bounded (413 naming the array).
A body that is not a zip archive is a 400 (``body``); a member that is corrupt, of an unknown name,
of a wrong dtype (complex, strings, objects, records) or shape is a 422 naming the array. The
arrays then go through the same request schema as a JSON body (same limits and messages).

NPZ answers (``Accept: application/x-npz``): each top-level field that is a list of numbers
becomes a float64 array (``mean``, ``lower``, ``upper``, ``std``, ...; ``null`` becomes NaN), a
number a 0-d array, a string a 0-d unicode array; the other fields (lists of strings, objects,
booleans, ``null``) go into one 0-d unicode array ``json`` holding a JSON object. Read it with
``numpy.load(io.BytesIO(body), allow_pickle=False)``.

ETags: ``etag_of(body)`` is a weak validator (``W/"<sha256 prefix>"``: the same answer gzip-encoded
or not); ``not_modified(request, etag)`` is true when ``If-None-Match`` lists it (or ``*``).
"""
from __future__ import annotations

import hashlib
import io
import json
import re
import zipfile

import numpy as np

from gpnarx.storage.archive_bounds import ArchiveError, open_archive
from gpnarx.storage.record_formats import NPY_READ_ERRORS, npy_header

from .problems import ProblemError

#: answers at least this long [bytes] are gzip-compressed for a client that sends Accept-Encoding: gzip
GZIP_MIN_BYTES = 1024
#: zlib level of those answers (1: fastest)
GZIP_LEVEL = 1
NPZ_MEDIA_TYPE = "application/x-npz"
#: the generic binary type, taken as an NPZ request body too (the one the OpenAPI document names for it)
OCTET_STREAM = "application/octet-stream"
#: the content types of an NPZ request body
NPZ_BODY_MEDIA_TYPES = (NPZ_MEDIA_TYPE, OCTET_STREAM)
#: arrays an NPZ request body may hold
NPZ_ARRAYS = ("u", "y", "y0")
#: string members of the package's own record files an NPZ body may hold: unit labels (checked against the
#: model's) and the record's name (ignored)
NPZ_METADATA = ("units_u", "units_y", "name")
#: longest such string [characters]
MAX_METADATA_CHARS = 256
#: members an NPZ body may hold (more is a 422)
MAX_MEMBERS = 8
#: largest .npy header read from a request [bytes]
MAX_NPY_HEADER = 4096
_INT = re.compile(r"[+-]?\d+")


# ---------------------------------------------------------------------------------------- requests
def _bad(field: str, detail: str, status: int = 422, **extra) -> ProblemError:
    return ProblemError(status, f"{field}: {detail}", field, **extra)


def _member_name(info: zipfile.ZipInfo) -> str:
    name = info.filename
    return name[:-4] if name.endswith(".npy") else name


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, field: str):
    """(shape, dtype, header bytes) of one member, read from its first bytes only (``storage.record_formats.
    npy_header``, as the record upload reads its members)."""
    try:
        with zf.open(info) as fh:
            head = npy_header(fh, MAX_NPY_HEADER)
            if head is None:
                raise ValueError("the member does not start with the .npy magic")
            return head[0], head[1], fh.tell()
    except NPY_READ_ERRORS as exc:  # a damaged archive or member
        raise _bad(field, f"not a readable .npy array in the archive ({type(exc).__name__}: {exc})"[:300]) from None


def read_npz_body(raw: bytes, max_bytes: int, max_samples: int, units: dict | None = None) -> dict:
    """The fields of an NPZ request body (arrays as lists, ``fs`` as a float): see the module doc.

    max_bytes: bound on the decompressed size of all members together [bytes]; max_samples: bound on
    the samples of one array; units: a dict that receives the archive's unit labels (``{"u": ..., "y": ...}``,
    those it holds) for ``check_units``. Raises ``ProblemError`` (400, 413 or 422) naming the array.
    """
    try:
        zf = open_archive(raw, MAX_MEMBERS)  # the directory's entries counted before zipfile reads them
    except ArchiveError as exc:
        raise ProblemError(422, f"{exc} (arrays {', '.join(NPZ_ARRAYS)} and fs)", "body", limit=MAX_MEMBERS) \
            from None
    except NPY_READ_ERRORS as exc:  # a damaged archive or member
        raise ProblemError(400, f"the {NPZ_MEDIA_TYPE} body is not a zip archive (.npz): {exc}"[:300], "body") \
            from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        declared = sum(i.file_size for i in infos)
        if declared > max_bytes:
            worst = max(infos, key=lambda i: i.file_size)
            raise _bad(_member_name(worst), f"the archive decompresses to {declared} bytes; the limit is "
                                            f"{max_bytes} bytes (GPNARX_MAX_BODY_BYTES)", 413, limit=max_bytes)
        out: dict = {}
        seen: set = set()
        for info in infos:
            field = _member_name(info)
            if field not in (*NPZ_ARRAYS, "fs", *NPZ_METADATA):
                raise _bad(field, f"unexpected array in the archive; an NPZ body holds {', '.join(NPZ_ARRAYS)} "
                                  f"and fs (the other fields are query parameters), and may hold the metadata "
                                  f"{', '.join(NPZ_METADATA)} of a record file")
            if field in seen:
                raise _bad(field, "appears twice in the archive")
            seen.add(field)
            shape, dtype, header = _npy_header(zf, info, field)
            if field in NPZ_METADATA:
                label = _metadata(zf, info, field, shape, dtype, header)
                if field != "name" and units is not None:
                    units[field.removeprefix("units_")] = label
                continue
            if dtype.hasobject or dtype.names is not None or dtype.kind not in "iuf":
                raise _bad(field, f"must be an integer or floating-point array, got dtype {dtype.str!r}")
            count = int(np.prod(shape, dtype=np.int64)) if shape else 1
            nbytes = count * dtype.itemsize
            if field != "fs" and count > max_samples:
                raise _bad(field, f"holds {count} samples; the limit is {max_samples} (GPNARX_MAX_SAMPLES)", 413,
                           limit=max_samples)
            if nbytes + header != info.file_size:  # the directory and the .npy header disagree
                raise _bad(field, f"corrupt array: its header says {nbytes} data bytes, the archive "
                                  f"{info.file_size - header}")
            try:
                with zf.open(info) as fh:
                    arr = np.lib.format.read_array(fh, allow_pickle=False, max_header_size=MAX_NPY_HEADER)
            except NPY_READ_ERRORS as exc:  # a damaged archive or member
                raise _bad(field, f"corrupt array in the archive ({type(exc).__name__}: {exc})"[:300]) from None
            if field == "fs":
                if arr.size != 1:
                    raise _bad("fs", f"must be a scalar sampling frequency in Hz, got shape {arr.shape}")
                out["fs"] = float(arr.reshape(()))
            else:
                if arr.ndim != 1:
                    raise _bad(field, f"must be a 1-D array, got shape {arr.shape}")
                arr = arr.astype(np.float64, copy=False)
                out[field] = arr.tolist()
                if field in ("u", "y") and np.isnan(arr).any():  # a gap (model.gaps): null, as in a JSON body
                    for i in np.flatnonzero(np.isnan(arr)):
                        out[field][i] = None
        return out


def _metadata(zf: zipfile.ZipFile, info: zipfile.ZipInfo, field: str, shape, dtype, header: int) -> str:
    """A metadata member's string (``NPZ_METADATA``), its size checked from the header before it is read."""
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if dtype.kind != "U" or count != 1:
        raise _bad(field, f"must be one unicode string (a record file's metadata), got dtype {dtype.str!r} "
                          f"shape {tuple(shape)}")
    chars = dtype.itemsize // 4
    if chars > MAX_METADATA_CHARS:
        raise _bad(field, f"holds {chars} characters; the limit is {MAX_METADATA_CHARS}", limit=MAX_METADATA_CHARS)
    if dtype.itemsize + header != info.file_size:
        raise _bad(field, f"corrupt array: its header says {dtype.itemsize} data bytes, the archive "
                          f"{info.file_size - header}")
    try:
        with zf.open(info) as fh:
            arr = np.lib.format.read_array(fh, allow_pickle=False, max_header_size=MAX_NPY_HEADER)
    except NPY_READ_ERRORS as exc:
        raise _bad(field, f"corrupt array in the archive ({type(exc).__name__}: {exc})"[:300]) from None
    return str(arr.reshape(()).item())


def check_units(units: dict, bundle) -> None:
    """The unit labels of an NPZ body (``read_npz_body``'s ``units``) against the model's (manifest ``units``): a
    label that is stated on both sides must name the same unit (``storage.record_formats.normalize_unit``
    spellings: ``N`` and ``newton`` agree); an empty label on either side is not checked. A 422 naming
    ``units_u`` or ``units_y`` otherwise: the record must be converted to the model's units first."""
    from gpnarx.storage.record_formats import RecordFileError, normalize_unit

    model = (getattr(bundle, "manifest", None) or {}).get("units") or {}
    for key, label in units.items():
        field = f"units_{key}"
        try:
            given = normalize_unit(label, field)
        except RecordFileError as exc:
            raise _bad(field, f"{exc.problem}"[:300]) from None
        try:
            expected = normalize_unit(model.get(key), "model")
        except RecordFileError:  # a label the model's trainer wrote but this package does not know: compare as is
            expected = str(model.get(key) or "").strip()
        if given and expected and given != expected:
            raise _bad(field, f"the record's {'input' if key == 'u' else 'output'} is in {label!r}, the model "
                              f"{bundle.name}:{bundle.version} takes {model.get(key)!r}; convert the record to the "
                              f"model's units first")


def query_fields(params) -> dict:
    """Query parameters as body fields: integers, numbers, ``true``/``false``, else strings.

    The request schema then checks each (a wrong type or an unknown name is a 422 naming it).
    """
    out: dict = {}
    for key, value in params.multi_items():
        if key in out:
            raise ProblemError(422, f"{key}: given more than once in the query", key)
        v: object = value
        if _INT.fullmatch(value):
            v = int(value)
        elif value in ("true", "false"):
            v = value == "true"
        else:
            try:
                f = float(value)
            except ValueError:
                pass
            else:
                if key in ("fs", "confidence"):
                    v = f
        out[key] = v
    return out


def npz_request_fields(raw: bytes, params, max_bytes: int, max_samples: int, units: dict | None = None) -> dict:
    """The JSON-equivalent body of an NPZ request: the archive's arrays and the query's fields (``units``: receives
    the archive's unit labels, ``read_npz_body``)."""
    body = read_npz_body(raw, max_bytes, max_samples, units)
    extra = query_fields(params)
    for key in extra:
        if key in body:
            raise ProblemError(422, f"{key}: given both in the archive and in the query", key)
    return {**body, **extra}


# ---------------------------------------------------------------------------------------- answers
def _numeric_list(v) -> bool:
    return isinstance(v, list) and bool(v) and all(
        x is None or (isinstance(x, (int, float)) and not isinstance(x, bool)) for x in v)


def render_npz(content: dict) -> bytes:
    """An answer as an NPZ archive (see the module doc); uncompressed, so it is cheap to write."""
    arrays: dict = {}
    rest: dict = {}
    for key, v in content.items():
        if isinstance(v, np.ndarray) and v.dtype.kind in "iuf":
            arrays[key] = v
        elif _numeric_list(v):
            arrays[key] = np.array([np.nan if x is None else x for x in v], dtype=np.float64)
        elif isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
            arrays[key] = np.asarray(v)
        elif isinstance(v, str):
            arrays[key] = np.asarray(v)
        else:
            rest[key] = v
    if rest:
        from gpnarx.storage.jsonsafe import dumps_json

        arrays["json"] = np.asarray(dumps_json(rest).decode())
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def wants_npz(accept: str | None) -> bool:
    """True when the Accept header prefers NPZ: listed with a non-zero quality, and not below the quality it
    gives ``application/json`` itself (wildcards do not count against NPZ; a tie goes to NPZ)."""
    if not accept:
        return False
    quality: dict[str, float] = {}
    for part in accept.split(",")[:64]:
        bits = [b.strip() for b in part.split(";")]
        q = next((b[2:] for b in bits[1:] if b.lower().startswith("q=")), "1")
        try:
            quality.setdefault(bits[0].lower(), float(q))
        except ValueError:
            quality.setdefault(bits[0].lower(), 0.0)
    npz = quality.get(NPZ_MEDIA_TYPE, 0.0)
    return npz > 0 and npz >= quality.get("application/json", 0.0)


# ---------------------------------------------------------------------------------------- ETags
def etag_of(body: bytes) -> str:
    """A weak ETag of an answer's bytes."""
    return f'W/"{hashlib.sha256(body).hexdigest()[:32]}"'


def not_modified(if_none_match: str | None, etag: str) -> bool:
    """True when ``If-None-Match`` names ``etag`` (weak comparison) or is ``*``."""
    if not if_none_match:
        return False
    ours = etag.removeprefix("W/")
    for tag in if_none_match.split(","):
        tag = tag.strip()
        if tag == "*" or tag.removeprefix("W/") == ours:
            return True
    return False


#: Cache-Control of what never changes for a version (its training report): a year, immutable
IMMUTABLE = "max-age=31536000, immutable"
#: Cache-Control of a version's metadata: it also lists the model's versions and aliases, which change, so a
#: cache revalidates with its ETag (a 304 when nothing changed)
REVALIDATE = "no-cache"


def json_loads_npz_meta(arr) -> dict:
    """The ``json`` member of an NPZ answer as a dict (for clients and tests)."""
    return json.loads(str(np.asarray(arr).item()))
