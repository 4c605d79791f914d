"""Record formats of data-acquisition software, read with optional packages (extra ``formats``).

``storage.record_formats.parse_record`` dispatches here by extension; each reader takes the file's
contents (a seekable binary file) and returns the pieces ``record_formats._make`` builds a
:class:`Record` from. The optional packages are imported when a file of their format is read; a
missing one raises :class:`LabFormatError` naming the extra (``pip install 'gpnarx[formats]'``), which
``record_formats`` turns into a ``RecordFileError`` naming the file (this module imports nothing of it).

How u, y and fs are found:

- **UFF-58** (``.uff``, ``.unv``; Simcenter / LMS Test.Lab universal files, ASCII or binary, read
  with pyuff): the type-58 (function) data sets whose ``id1`` (the first ID line) is ``u`` and ``y``
  (case-insensitive); a file with exactly one or two type-58 sets and no such names is read as u
  then y. fs = 1 / ``abscissa_inc`` [s], rounded to 6 significant digits (the ASCII header keeps 6);
  both sets must be evenly spaced (``abscissa_spacing`` 1) with the same increment and length.
  Units: ``ordinate_axis_units_lab`` (kept in ``meta`` when it is not a known unit).
- **TDMS** (``.tdms``; NI LabVIEW / DAQmx, read with npTDMS): the channels named ``u`` and ``y``
  (case-insensitive) of the first group that has a ``u``; fs = 1 / ``wf_increment`` [s] (the NI
  waveform property), else a ``fs`` property [Hz] of the channel, its group or the file. Units: the
  channel property ``unit_string``.
- **HDF5 and MATLAB v7.3** (``.h5``, ``.hdf5``, and ``.mat`` files saved with ``-v7.3``; read with
  h5py): the datasets ``u``, ``y`` (optional) and ``fs`` (scalar [Hz]) at the root, as MATLAB
  writes the variables ``u``, ``y``, ``fs`` (an ``n x 1`` or ``1 x n`` vector is fine); ``fs`` may
  instead be an attribute of the root or of ``u``. Units: the MATLAB char variables ``units_u`` /
  ``units_y`` or a ``units`` attribute of each dataset.

A unit label that is not one of ``record_formats.KNOWN_UNITS`` is read as "not stated" and kept in
``Record.meta`` (``u_unit_label``, ``y_unit_label``): lab software spells units its own way.
"""
from __future__ import annotations

import importlib
import math
import os
import tempfile
import zlib

import numpy as np

#: extension -> (format name, the optional package it needs, its import name)
LAB_FORMATS = {
    ".uff": ("UFF-58", "pyuff", "pyuff"),
    ".unv": ("UFF-58", "pyuff", "pyuff"),
    ".tdms": ("TDMS", "npTDMS", "nptdms"),
    ".h5": ("HDF5", "h5py", "h5py"),
    ".hdf5": ("HDF5", "h5py", "h5py"),
}
EXTRA = "formats"


class LabFormatError(ValueError):
    """A lab file cannot be read; ``record_formats`` turns it into a ``RecordFileError`` naming the file."""


def need(p, module: str, package: str, what: str):
    """The optional module ``module``, or a LabFormatError naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise LabFormatError(f"reading {what} files needs the optional package {package}: "
                                 f"pip install 'gpnarx[{EXTRA}]'") from None


# ---------------------------------------------------------------------------------------- UFF-58
def read_uff(p, fh) -> dict:
    """u, y, fs, units and meta of a UFF-58 file (see the module doc)."""
    pyuff = need(p, "pyuff", "pyuff", "UFF-58")
    # pyuff reads a named file: the contents go to a temporary one, removed at once
    fd, tmp = tempfile.mkstemp(suffix=".uff")
    try:
        with os.fdopen(fd, "wb") as out:
            fh.seek(0)
            while chunk := fh.read(1 << 20):
                out.write(chunk)
        uff = pyuff.UFF(tmp)
        types = [int(t) for t in np.atleast_1d(uff.get_set_types())]
        sets = [uff.read_sets(i) for i, t in enumerate(types) if t == 58]
    finally:
        os.unlink(tmp)
    if not sets:
        raise LabFormatError(f"no UFF-58 (function) data set in the file (set types: "
                                 f"{', '.join(map(str, types)) or 'none'})")
    by_name = {str(s.get("id1", "")).strip().lower(): s for s in sets}
    if "u" in by_name:
        su, sy = by_name["u"], by_name.get("y")
    elif len(sets) <= 2:
        su, sy = sets[0], (sets[1] if len(sets) == 2 else None)
    else:
        names = ", ".join(repr(str(s.get("id1", "")).strip()) for s in sets)
        raise LabFormatError(f"{len(sets)} UFF-58 data sets and none named 'u' in its first ID line "
                                 f"(id1: {names}); name the input 'u' and the output 'y'")
    incs = []
    for label, s in (("u", su), ("y", sy)):
        if s is None:
            continue
        if int(s.get("abscissa_spacing", 1)) != 1:
            raise LabFormatError(f"{label}: uneven abscissa (abscissa_spacing 0); a record needs even sampling")
        inc = float(s.get("abscissa_inc", 0.0))
        if not math.isfinite(inc) or inc <= 0:
            raise LabFormatError(f"{label}: abscissa_inc must be a positive sample period in s, got {inc!r}")
        incs.append(inc)
        if np.iscomplexobj(s.get("data")):
            raise LabFormatError(f"{label}: complex data (a spectrum or FRF?); a time record is required")
        declared, held = s.get("num_pts"), int(np.size(s.get("data")))
        if declared is not None and int(declared) != held:
            raise LabFormatError(f"{label}: the data set declares {int(declared)} points (num_pts), the file holds "
                                 f"{held} (truncated or corrupt)")
    if len(incs) == 2 and abs(incs[0] - incs[1]) > 1e-5 * incs[0]:
        raise LabFormatError(f"u and y have different sample periods ({incs[0]:g} s and {incs[1]:g} s)")
    fs = float(f"{1.0 / incs[0]:.6g}")
    units = {"u": str(su.get("ordinate_axis_units_lab") or "").strip(),
             "y": "" if sy is None else str(sy.get("ordinate_axis_units_lab") or "").strip()}
    meta = {"format": "uff-58", "u_id": str(su.get("id1", "")).strip(),
            "y_id": "" if sy is None else str(sy.get("id1", "")).strip()}
    return {"u": np.asarray(su["data"]), "y": None if sy is None else np.asarray(sy["data"]), "fs": fs,
            "units": units, "meta": meta}


# ---------------------------------------------------------------------------------------- TDMS
def read_tdms(p, fh) -> dict:
    """u, y, fs, units and meta of a TDMS file (see the module doc)."""
    nptdms = need(p, "nptdms", "npTDMS", "TDMS")
    fh.seek(0)
    tdms = nptdms.TdmsFile.read(fh)
    group = None
    for g in tdms.groups():
        names = {c.name.strip().lower(): c for c in g.channels()}
        if "u" in names:
            group, chans = g, names
            break
    if group is None:
        found = ", ".join(f"{g.name}/{c.name}" for g in tdms.groups() for c in g.channels()) or "none"
        raise LabFormatError(f"no channel named 'u' in any group (channels: {found[:300]})")
    cu, cy = chans["u"], chans.get("y")
    fs = None
    for source in (cu, group, tdms):
        props = source.properties
        if source is cu and props.get("wf_increment"):
            inc = float(props["wf_increment"])
            if not math.isfinite(inc) or inc <= 0:
                raise LabFormatError(f"u: wf_increment must be a positive sample period in s, got {inc!r}")
            fs = float(f"{1.0 / inc:.12g}")
            break
        if "fs" in props:
            fs = float(props["fs"])
            break
    if cy is not None and cu.properties.get("wf_increment") and cy.properties.get("wf_increment"):
        a, b = float(cu.properties["wf_increment"]), float(cy.properties["wf_increment"])
        if abs(a - b) > 1e-9 * a:
            raise LabFormatError(f"u and y have different wf_increment ({a:g} s and {b:g} s)")
    units = {"u": str(cu.properties.get("unit_string") or "").strip(),
             "y": "" if cy is None else str(cy.properties.get("unit_string") or "").strip()}
    return {"u": cu[:], "y": None if cy is None else cy[:], "fs": fs, "units": units,
            "meta": {"format": "tdms", "group": group.name}}


# ---------------------------------------------------------------------------------------- HDF5 / MAT v7.3
def _h5_string(ds) -> str:
    """A MATLAB char variable (uint16 codes) or an HDF5 string as str."""
    a = ds[()]
    if isinstance(a, bytes):
        return a.decode("utf-8", "replace")
    if isinstance(a, str):
        return a
    a = np.asarray(a)
    if a.dtype.kind in "iu":
        return "".join(chr(int(c)) for c in a.ravel() if int(c))
    if a.dtype.kind == "S":
        return b"".join(a.ravel().tolist()).decode("utf-8", "replace")
    return str(a.ravel()[0]) if a.size else ""


def _attr_str(v) -> str:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    a = np.asarray(v)
    if a.dtype.kind == "S":
        return b"".join(a.ravel().tolist()).decode("utf-8", "replace")
    return str(a.ravel()[0]) if a.size else ""


#: the datasets ``read_hdf5`` reads (when they are datasets at the root)
HDF5_READ = ("u", "y", "fs", "units_u", "units_y")


#: HDF5 filters a chunk may be stored with (their ids): deflate (gzip; each stored chunk inflated here first, at most
#: to its chunk size, as HDF5's own filter inflates whatever the stream holds), shuffle and fletcher32 (their output
#: is their input's size). The others (LZF, SZIP, scale-offset, N-bit, plug-ins) size their output from what the
#: file says, unchecked: refused
H5_DEFLATE, H5_SHUFFLE, H5_FLETCHER32 = 1, 2, 3
H5_FILTERS = {H5_DEFLATE: "deflate (gzip)", H5_SHUFFLE: "shuffle", H5_FLETCHER32: "fletcher32"}


def _h5_open(fh):
    """The h5py module and ``fh`` opened read-only, or None when h5py is missing or cannot open it (``read_hdf5``
    then fails the same way, before reading a dataset)."""
    try:
        import h5py
    except ImportError:
        return None
    fh.seek(0)
    try:
        return h5py, h5py.File(fh, "r")
    except Exception:  # noqa: BLE001 - read_hdf5 reports it
        return None


def _stored_chunks(ds) -> list:
    """StoreInfo (chunk_offset, filter_mask, byte_offset, size) of each stored chunk of the chunked dataset ``ds``."""
    if hasattr(ds.id, "chunk_iter"):
        out: list = []
        ds.id.chunk_iter(out.append)
        return out
    return [ds.id.get_chunk_info(i) for i in range(ds.id.get_num_chunks())]


def hdf5_arrays(fh) -> list:
    """(name, values, bytes) of what reading each dataset ``read_hdf5`` reads inflates and allocates, from the
    dataset's shape, item size and chunk layout alone (nothing is read): the dataset itself (shape x item size: a
    chunked dataset may be compressed, or never written and read as its fill value, and reading it allocates its
    declared size), and for a chunked dataset its stored chunks, each inflated whole at its chunk shape x item size
    (named ``dataset 'NAME' (N stored chunks of B bytes)``). Empty when h5py is missing or cannot open the file."""
    opened = _h5_open(fh)
    if opened is None:
        return []
    h5py, f = opened
    out = []
    with f:
        for key in HDF5_READ:
            ds = f.get(key)
            if not isinstance(ds, h5py.Dataset):
                continue
            count = int(ds.size or 0)
            out.append((key, count, count * ds.dtype.itemsize))
            if ds.chunks is not None:
                chunk = math.prod(ds.chunks) * ds.dtype.itemsize
                stored = ds.id.get_num_chunks()
                out.append((f"dataset '{key}' ({stored} stored chunk{'s' if stored != 1 else ''} of {chunk} bytes)",
                            0, stored * chunk))
    return out


def hdf5_chunk_check(fh) -> None:
    """LabFormatError when a stored chunk of a dataset ``read_hdf5`` reads would inflate past its chunk size, or uses
    a filter whose decoded size is not checked (``H5_FILTERS``). Each deflate stream is inflated here in pieces of
    1 MiB, discarded, at most to its chunk size (call it once ``hdf5_arrays``' sizes are within bounds: it inflates
    what they declare)."""
    opened = _h5_open(fh)
    if opened is None:
        return
    h5py, f = opened
    with f:
        for key in HDF5_READ:
            ds = f.get(key)
            if not isinstance(ds, h5py.Dataset) or ds.chunks is None:
                continue
            plist = ds.id.get_create_plist()
            filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
            other = [plist.get_filter(i)[3].decode(errors="replace") or str(code)
                     for i, code in enumerate(filters) if code not in H5_FILTERS]
            if other:
                raise LabFormatError(f"dataset '{key}' is stored with the HDF5 filter {other[0]!r}, whose decoded size "
                                     f"is not checked before reading; records read {', '.join(H5_FILTERS.values())} "
                                     f"(save it with compression='gzip')")
            if H5_DEFLATE not in filters:
                continue
            at = filters.index(H5_DEFLATE)
            if H5_SHUFFLE in filters[at + 1:]:
                raise LabFormatError(f"dataset '{key}' shuffles its chunks after compressing them; records read "
                                     f"chunks shuffled, then compressed (as h5py and MATLAB write them)")
            checksum = 1 << filters.index(H5_FLETCHER32) if H5_FLETCHER32 in filters[at + 1:] else 0
            size = math.prod(ds.chunks) * ds.dtype.itemsize
            for info in _stored_chunks(ds):
                mask, raw = ds.id.read_direct_chunk(info.chunk_offset)
                if mask & (1 << at):  # stored without deflate
                    continue
                if checksum and not mask & checksum:
                    raw = raw[:-4]
                if _inflates_past(raw, size):
                    raise LabFormatError(f"dataset '{key}': a stored chunk inflates past the {size} bytes of its chunk "
                                         f"(chunk shape {ds.chunks}, {ds.dtype}): a corrupt or forged file")


def _inflates_past(stream: bytes, size: int) -> bool:
    """Whether the zlib ``stream`` inflates to more than ``size`` bytes (inflated 1 MiB at a time, discarded; a
    damaged stream is left to HDF5, which fails on it)."""
    d = zlib.decompressobj()
    out = 0
    try:
        while stream and not d.eof:
            out += len(d.decompress(stream, 1 << 20))
            if out > size:
                return True
            if not d.unconsumed_tail and not d.eof:
                out += len(d.flush())
                break
            stream = d.unconsumed_tail
    except zlib.error:
        return False
    return out > size


def _refuse_outside_data(h5py, f) -> None:
    """LabFormatError when a root entry the reader may open keeps its data outside the file: an external link, a
    dataset in external raw files or a virtual dataset would make a parse read other files of the machine that
    parses it (a server's, for an uploaded file)."""
    for key in HDF5_READ:
        link = f.get(key, getlink=True)
        if isinstance(link, h5py.ExternalLink):
            raise LabFormatError(f"'{key}' is an external link to {link.filename!r}: only data inside the file is read")
        obj = f.get(key) if link is not None else None
        if isinstance(obj, h5py.Dataset) and (obj.external or obj.is_virtual):
            raise LabFormatError(f"dataset '{key}' keeps its data outside the file (external or virtual storage): "
                                 f"only data inside the file is read")


def read_hdf5(p, fh) -> dict:
    """u, y, fs, units and meta of an HDF5 / MATLAB v7.3 file (see the module doc); data kept outside the file
    (external links, external or virtual storage) is refused."""
    h5py = need(p, "h5py", "h5py", "HDF5 / MATLAB v7.3")
    fh.seek(0)
    with h5py.File(fh, "r") as f:
        _refuse_outside_data(h5py, f)
        keys = sorted(f.keys())
        if "u" not in f or not isinstance(f["u"], h5py.Dataset):
            raise LabFormatError(f"missing dataset 'u' at the root (datasets and groups: "
                                     f"{', '.join(keys) or 'none'})")
        matlab = "MATLAB_class" in f["u"].attrs
        u = np.asarray(f["u"][()])
        y = np.asarray(f["y"][()]) if "y" in f and isinstance(f["y"], h5py.Dataset) else None
        fs = None
        if "fs" in f and isinstance(f["fs"], h5py.Dataset):
            fs = f["fs"][()]
        elif "fs" in f.attrs:
            fs = f.attrs["fs"]
        elif "fs" in f["u"].attrs:
            fs = f["u"].attrs["fs"]
        if fs is not None:
            a = np.asarray(fs)
            if a.size != 1 or a.dtype.kind not in "biuf":
                raise LabFormatError(f"fs must be a numeric scalar, got shape {a.shape} dtype {a.dtype}")
            fs = float(a.reshape(()))
        units = {}
        for k in ("u", "y"):
            if f"units_{k}" in f and isinstance(f[f"units_{k}"], h5py.Dataset):
                units[k] = _h5_string(f[f"units_{k}"])
            elif k in f and "units" in f[k].attrs:
                units[k] = _attr_str(f[k].attrs["units"])
            else:
                units[k] = ""
    return {"u": u, "y": y, "fs": fs, "units": units,
            "meta": {"format": "matlab-v7.3" if matlab else "hdf5"}}
