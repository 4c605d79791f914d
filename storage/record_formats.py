"""Record file formats parsed from their contents: CSV, NPZ, NPY, MATLAB .mat (v5, and v7.3 with the
extra ``formats``), LMS Test.Lab, and with the extra ``formats`` UFF-58, TDMS and HDF5
(``storage.record_formats_lab``).

No filesystem access here: callers hand over the bytes (or an open binary file) and a file name
that picks the format. ``storage.record_files.read_record`` opens files and LMS folders and calls
these parsers; the service parses uploaded files with them (``POST /v1/records/parse``). The
formats are documented in ``storage.record_files``.

- :func:`parse_record` ``(data, filename, fs=None, name=None, fs_default=None, source=None)``:
  ``.csv``, ``.npz``, ``.npy``, ``.mat``, ``.uff``/``.unv``, ``.tdms`` or ``.h5``/``.hdf5`` by the
  extension of ``filename``.
- :func:`parse_lms` ``(shaker, time, ...)``: the two files of an LMS Test.Lab export
  (``TimeShaker.mat``: input u, ``Time.mat``: output y).
- :func:`check_bounds` ``(data, filename, max_samples=, max_bytes=)``: refuse, from the file's headers and
  directory alone (nothing decompressed or allocated from a declared size), a file whose parse would load
  more than ``max_samples`` samples per signal or decompress more than ``max_bytes`` bytes
  (:class:`RecordTooLarge`); ``parse_record`` and ``parse_lms`` call it when given those limits.

``source`` names the file in every error message and in ``Record.meta["source"]`` (default: the
file name). Every problem raises :class:`RecordFileError` (a ``ValueError``) with one line naming
the source and the problem.
"""
from __future__ import annotations

import csv
import io
import math
import re
import struct
import zipfile
import zlib
from pathlib import PurePath

import numpy as np

from gpnarx.model.record import MAX_CHANNELS, Channel, Record, RecordError, gaps_allowed

from .archive_bounds import NPY_READ_ERRORS, ArchiveError, member, npy_header, open_archive
from .record_formats_lab import LAB_FORMATS

__all__ = [
    "RecordFileError",
    "RecordTooLarge",
    "NoSamplingFrequency",
    "KNOWN_UNITS",
    "FORMATS",
    "LMS_INPUT",
    "LMS_OUTPUT",
    "normalize_unit",
    "check_fs",
    "parse_record",
    "parse_lms",
    "parse_lms_channels",
    "lms_channels",
    "LMS_MKS_UNITS",
    "check_bounds",
    "npy_header",
    "NPY_READ_ERRORS",
]

# Unit labels accepted on records (normalised spelling). Empty string = not stated.
KNOWN_UNITS = frozenset(
    {
        "", "N", "kN", "mN", "V", "mV", "A",
        "m", "mm", "um", "m/s", "mm/s", "m/s^2", "mm/s^2", "g",
        "rad", "deg", "Pa", "N m", "s", "-",
    }
)
_UNIT_ALIASES = {
    "m/s2": "m/s^2", "m/s²": "m/s^2", "m s^-2": "m/s^2", "m/s/s": "m/s^2", "ms^-2": "m/s^2",
    "mm/s2": "mm/s^2", "mm/s²": "mm/s^2",
    "m s^-1": "m/s", "ms^-1": "m/s",
    "µm": "um", "μm": "um", "micron": "um",
    "nm": None,  # explicitly unknown (listed so the message stays generic)
    "newton": "N", "volt": "V", "v": "V", "n": "N", "Nm": "N m", "N.m": "N m", "N*m": "N m",
    "g0": "g", "G": "g", "none": "", "1": "-",
}

#: Extensions :func:`parse_record` reads (those of ``LAB_FORMATS`` need the extra ``formats``).
FORMATS = (".csv", ".npz", ".npy", ".mat", *LAB_FORMATS)
#: How an unsupported-format message lists what is read.
FORMATS_TEXT = ", ".join(FORMATS) + " or an LMS folder"
#: (file name, struct name) of the input and output channels of an LMS Test.Lab export.
LMS_INPUT = ("TimeShaker.mat", "Time_Shaker__X")
LMS_OUTPUT = ("Time.mat", "Time_Laser__X")
_FS_RTOL = 1e-3


class RecordFileError(RecordError):
    """A record file cannot be read or written; the message is one line naming the file."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = _one_line(problem)
        super().__init__(f"{self.path}: {self.problem}")


def _one_line(text) -> str:
    return " ".join(str(text).split())


def normalize_unit(label, path="<units>") -> str:
    """Return the normalised spelling of a unit label, or raise :class:`RecordFileError`."""
    if label is None:
        return ""
    if isinstance(label, np.ndarray):
        label = label.item() if label.size == 1 else "".join(map(str, label.ravel()))
    if isinstance(label, bytes):
        label = label.decode("utf-8", "replace")
    lab = str(label).strip()
    if lab in KNOWN_UNITS:
        return lab
    alias = _UNIT_ALIASES.get(lab, _UNIT_ALIASES.get(lab.lower(), "?"))
    if alias not in (None, "?"):
        return alias
    if lab.lower() in {u.lower() for u in KNOWN_UNITS if len(u) > 1}:
        return next(u for u in KNOWN_UNITS if u.lower() == lab.lower())
    raise RecordFileError(
        path, f"unknown unit label {lab!r} (known: {', '.join(sorted(u for u in KNOWN_UNITS if u))})"
    )


# ============================================================================ entry points
def _binary(data):
    if isinstance(data, (bytes, bytearray, memoryview)):
        return io.BytesIO(bytes(data))
    if not hasattr(data, "read") or not hasattr(data, "seek"):
        raise TypeError(f"expected bytes or a seekable binary file, got {type(data).__name__}")
    return data


class NoSamplingFrequency(RecordFileError):
    """A record file without a sampling frequency (a CSV without a time column, an NPY) read without ``fs``
    or ``fs_default``: the caller names its own option (``--fs``, the parse form's ``fs`` field)."""


def parse_record(data, filename: str, *, fs=None, name=None, fs_default=None, source=None,
                 max_samples=None, max_bytes=None) -> Record:
    """Parse the contents of a record file into a :class:`Record`.

    data: bytes or a seekable binary file. filename: its name; the extension picks the format
    (``FORMATS``). fs: sampling frequency [Hz]; required when the file
    has none, checked against the file's otherwise (0.1 %). fs_default: used only when the file
    carries no sampling information. name: record name (default: the file name's stem).
    source: what error messages and ``meta["source"]`` call the file (default: ``filename``).
    max_samples [samples per signal], max_bytes [bytes decompressed]: when given, :func:`check_bounds`
    refuses a larger file from its headers first (:class:`RecordTooLarge`). An LMS export needs both of
    its files: :func:`parse_lms`.
    """
    fname = PurePath(str(filename)).name
    src = fname if source is None else source
    if fs is not None:
        fs = check_fs(src, fs)
    if fs_default is not None and fs is None:
        fs_default = check_fs(src, fs_default)
    ext = PurePath(fname).suffix.lower()
    if ext not in FORMATS:
        raise RecordFileError(
            src, f"unsupported record format {PurePath(fname).suffix or '(no extension)'!r}; use {FORMATS_TEXT}"
        )
    stem = PurePath(fname).stem
    try:
        fh = _binary(data)
        if max_samples is not None or max_bytes is not None:
            check_bounds(fh, fname, max_samples=max_samples, max_bytes=max_bytes, source=src)
        if ext == ".csv":
            return _read_csv(src, fh, fs, name or stem, fs_default)
        if ext == ".npz":
            return _read_npz(src, fh, fs, name, stem)
        if ext == ".npy":
            return _read_npy(src, fh, fs, name or stem, fs_default)
        if ext in LAB_FORMATS:
            return _read_lab(src, fh, ext, fs, name or stem)
        return _read_mat(src, fh, fs, name or stem)
    except RecordFileError:
        raise
    except RecordError as exc:  # Record validation (NaN, shapes, fs)
        raise RecordFileError(src, _strip_name(str(exc))) from None
    except MemoryError:
        raise RecordFileError(src, "file too large to load") from None
    except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
        raise RecordFileError(src, f"cannot read the file ({type(exc).__name__}: {exc})") from None


def parse_lms(shaker, time, *, fs=None, name=None, source="LMS export", shaker_source=None,
              time_source=None, max_samples=None, max_bytes=None, inputs=None, outputs=None) -> Record:
    """Parse an LMS Test.Lab export from the contents of its two files (see ``storage.record_files``).

    shaker: ``TimeShaker.mat`` (input u, struct ``Time_Shaker__X``); time: ``Time.mat`` (output y,
    struct ``Time_Laser__X``); each bytes or a seekable binary file. source names the export in
    messages and ``meta["source"]``; shaker_source / time_source name the two files (default
    ``SOURCE/TimeShaker.mat`` and ``SOURCE/Time.mat``). name: record name (default: source's name).
    max_samples, max_bytes: as for :func:`parse_record`, checked on each file.
    inputs, outputs: channels to read by name (:func:`parse_lms_channels`: ``TimeShaker.mat``'s channels
    for u, ``Time.mat``'s for y, e.g. ``outputs=["Laser:+X", "Acc1:+X"]``), in that order; None (both):
    the shaker voltage and the laser velocity, the single-channel record of every release.
    """
    if inputs is not None or outputs is not None:
        return parse_lms_channels(shaker, time, fs=fs, name=name, source=source, shaker_source=shaker_source,
                                  time_source=time_source, max_samples=max_samples, max_bytes=max_bytes,
                                  inputs=inputs, outputs=outputs)
    if fs is not None:
        fs = check_fs(source, fs)
    pin = shaker_source if shaker_source is not None else f"{source}/{LMS_INPUT[0]}"
    pout = time_source if time_source is not None else f"{source}/{LMS_OUTPUT[0]}"
    try:
        if max_samples is not None or max_bytes is not None:
            shaker, time = _binary(shaker), _binary(time)
            for p, fh in ((pin, shaker), (pout, time)):
                check_bounds(fh, LMS_INPUT[0], max_samples=max_samples, max_bytes=max_bytes, source=p)
        cin = _lms_channel(pin, _binary(shaker), LMS_INPUT[1])
        cout = _lms_channel(pout, _binary(time), LMS_OUTPUT[1])
    except RecordFileError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(source, f"cannot read the LMS export ({type(exc).__name__}: {exc})") from None
    if abs(cin["increment"] - cout["increment"]) > 1e-9 * cin["increment"]:
        raise RecordFileError(
            source, f"sample periods differ: TimeShaker.mat {cin['increment']:g} s, Time.mat {cout['increment']:g} s"
        )
    if cin["values"].size != cout["values"].size:
        raise RecordFileError(
            source, f"TimeShaker.mat has {cin['values'].size} samples but Time.mat has {cout['values'].size}"
        )
    file_fs = float(f"{1.0 / cin['increment']:.12g}")
    fs = _reconcile_fs(source, file_fs, fs)
    meta = {
        "format": "lms-testlab",
        "input_channel": cin["meta"].get("channel", ""),
        "output_channel": cout["meta"].get("channel", ""),
        "run_name": cout["meta"].get("run_name", ""),
        "creation_time": cout["meta"].get("creation_time", ""),
    }
    return _make(source, cin["values"], cout["values"], fs, {"u": cin["unit"], "y": cout["unit"]},
                 name or PurePath(str(source)).name, meta)


def lms_channels(data, *, source="Time.mat", max_samples=None, max_bytes=None) -> list[dict]:
    """Every channel of one file of an LMS Test.Lab export (``Time.mat`` or ``TimeShaker.mat``), in file order.

    A struct with ``x_values`` and ``y_values`` holds one channel (``Time_Laser__X``: the laser) or, with
    (n, k) values, k channels (``Signal``: the accelerometers ``Acc1:+X`` to ``Acc4:+X``). Each channel is a
    dict: ``name`` (its ``function_record.primary_channel.label``, e.g. ``Laser:+X``, ``Acc1:+X``; the
    struct's name when it has none), ``struct`` (the struct's name, also accepted as the name of a
    single-channel struct: ``Time_Laser__X``), ``values`` (n,), ``unit`` and ``increment`` [s].

    The unit is what the values hold. Test.Lab saves values in MKS units and labels the quantity by its
    display unit, ``display = factor * value + offset`` (``y_values.quantity.unit_transformation``). When the
    quantity says so (``quantity.info`` "Data saved by Test.Lab in MKS") and its label has an MKS unit in
    ``LMS_MKS_UNITS`` (the accelerometers' ``g``: m/s^2), the values are kept and the unit is the MKS one:
    at 20 Hz, Acc1 equals the time derivative of the laser velocity [m/s] in m/s^2 (tests/test_mimo_records.py).
    Otherwise the transformation is applied and the unit is the label (the single-channel reader's rule;
    the laser [m/s] and the shaker [V] have factor 1). Bounded as :func:`parse_record`: the file by
    ``check_bounds`` (bytes), each channel's samples by ``max_samples``, and at most ``MAX_CHANNELS``
    columns per struct.
    """
    fh = _binary(data)
    if max_samples is not None or max_bytes is not None:
        check_bounds(fh, "Time.mat", max_samples=max_samples, max_bytes=max_bytes, source=source)
    d = _loadmat(source, fh)
    out = []
    for sname in sorted(k for k in d if not k.startswith("__")):
        s = d[sname]
        if not (hasattr(s, "_fieldnames") and "x_values" in s._fieldnames and "y_values" in s._fieldnames):
            continue
        out.extend(_lms_struct_channels(source, s, sname, max_samples))
    if not out:
        names = sorted(k for k in d if not k.startswith("__"))
        raise RecordFileError(source, f"no LMS channel in the file (variables: {', '.join(names) or 'none'})")
    # the laser first, as the export lists it; then the other structs in name order
    out.sort(key=lambda c: c["struct"] not in (LMS_OUTPUT[1], LMS_INPUT[1]))
    return out


#: the MKS unit of an LMS display-unit label, for quantities Test.Lab saved in MKS (``lms_channels``)
LMS_MKS_UNITS = {"g": "m/s^2", "m/s^2": "m/s^2", "m/s": "m/s", "m": "m", "V": "V", "N": "N", "mm/s": "m/s",
                 "mm": "m", "mm/s^2": "m/s^2", "kN": "N", "mV": "V"}


def _lms_struct_channels(p, s, sname: str, max_samples) -> list[dict]:
    inc = _scalar(p, _field(p, s, "x_values.increment"), f"{sname}.x_values.increment")
    if not math.isfinite(inc) or inc <= 0:
        raise RecordFileError(p, f"{sname}.x_values.increment must be a positive sample period in s, got {inc!r}")
    nval = int(_scalar(p, _field(p, s, "x_values.number_of_values"), f"{sname}.x_values.number_of_values"))
    if max_samples is not None and nval > max_samples:
        raise RecordTooLarge(p, sname, nval, max_samples, "samples")
    values = np.asarray(_field(p, s, "y_values.values"))
    if values.ndim == 1:
        values = values[:, None]
    if values.ndim != 2 or values.shape[0] != nval:
        raise RecordFileError(p, f"{sname}.y_values.values has shape {values.shape} but x_values.number_of_values "
                                 f"says {nval} samples (truncated?)")
    k = values.shape[1]
    if k > MAX_CHANNELS:
        raise RecordFileError(p, f"{sname} holds {k} channels; at most {MAX_CHANNELS} are read")
    q = _field(p, s, "y_values.quantity")
    label = _string(_field(p, q, "label"))
    info = _string(getattr(q, "info", "")) if hasattr(q, "_fieldnames") and "info" in q._fieldnames else ""
    factor, offset = 1.0, 0.0
    try:
        ut = _field(p, q, "unit_transformation")
        factor = float(getattr(ut, "factor", 1.0))
        offset = float(getattr(ut, "offset", 0.0))
    except (RecordFileError, TypeError, ValueError):
        pass
    if "MKS" in info and label in LMS_MKS_UNITS:
        unit, factor, offset = LMS_MKS_UNITS[label], 1.0, 0.0
    else:
        unit = normalize_unit(label, p)
    try:
        labels = np.atleast_1d(np.asarray(s.function_record.primary_channel.label, dtype=object)).ravel()
        labels = [str(x) for x in labels]
    except AttributeError:
        labels = []
    if len(labels) != k:
        labels = [sname] if k == 1 else [f"{sname}[{j}]" for j in range(k)]
    out = []
    for j in range(k):
        sig = _signal(p, values[:, j], f"{sname}.y_values.values[:, {j}]")
        if factor != 1.0 or offset != 0.0:
            sig = sig * factor + offset
        out.append({"name": labels[j], "struct": sname, "values": sig, "unit": unit, "increment": inc})
    return out


def _lms_find(p, chans: list[dict], wanted, file: str) -> list[dict]:
    if isinstance(wanted, str):
        wanted = [wanted]
    out = []
    for w in wanted:
        hit = [c for c in chans if c["name"] == w]
        if not hit:  # a single-channel struct by its struct's name (Time_Laser__X)
            hit = [c for c in chans if c["struct"] == w and sum(d["struct"] == w for d in chans) == 1]
        if not hit:
            raise RecordFileError(p, f"{file} has no channel {w!r} (channels: "
                                     f"{', '.join(repr(c['name']) for c in chans)})")
        if any(h is hit[0] for h in out):
            raise RecordFileError(p, f"channel {w!r} is selected twice")
        out.append(hit[0])
    if not out:
        raise RecordFileError(p, f"select at least one channel of {file}")
    return out


def parse_lms_channels(shaker, time, *, fs=None, name=None, source="LMS export", shaker_source=None,
                       time_source=None, max_samples=None, max_bytes=None, inputs=None, outputs=None) -> Record:
    """An LMS Test.Lab export as a record of the named channels (:func:`lms_channels`): u from
    ``TimeShaker.mat`` (``inputs``, default its first channel, the shaker voltage), y from ``Time.mat``
    (``outputs``, default the laser alone), each in the order named; one channel gives a 1-D u or y.
    ``Record.channels`` holds every selected channel's name and unit; ``units`` their common unit ("" when
    they differ). ``meta["input_channels"]`` / ``meta["output_channels"]`` list the names.
    """
    if fs is not None:
        fs = check_fs(source, fs)
    pin = shaker_source if shaker_source is not None else f"{source}/{LMS_INPUT[0]}"
    pout = time_source if time_source is not None else f"{source}/{LMS_OUTPUT[0]}"
    try:
        cins = lms_channels(shaker, source=pin, max_samples=max_samples, max_bytes=max_bytes)
        couts = lms_channels(time, source=pout, max_samples=max_samples, max_bytes=max_bytes)
    except RecordFileError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(source, f"cannot read the LMS export ({type(exc).__name__}: {exc})") from None
    sel_in = _lms_find(pin, cins, [cins[0]["name"]] if inputs is None else inputs, LMS_INPUT[0])
    sel_out = _lms_find(pout, couts, [couts[0]["name"]] if outputs is None else outputs, LMS_OUTPUT[0])
    inc = sel_in[0]["increment"]
    n = sel_in[0]["values"].size
    for c in sel_in + sel_out:
        if abs(c["increment"] - inc) > 1e-9 * inc:
            raise RecordFileError(source, f"sample periods differ: {sel_in[0]['name']} {inc:g} s, "
                                          f"{c['name']} {c['increment']:g} s")
        if c["values"].size != n:
            raise RecordFileError(source, f"{sel_in[0]['name']} has {n} samples but {c['name']} has "
                                          f"{c['values'].size}")
    fs = _reconcile_fs(source, float(f"{1.0 / inc:.12g}"), fs)

    def stack(sel):
        return sel[0]["values"] if len(sel) == 1 else np.column_stack([c["values"] for c in sel])

    chans = {"u": [Channel(c["name"], c["unit"]) for c in sel_in],
             "y": [Channel(c["name"], c["unit"]) for c in sel_out]}
    units = {k: (v[0].unit if len({c.unit for c in v}) == 1 else "") for k, v in chans.items()}
    meta = {"source": str(source), "format": "lms-testlab", "input_channel": sel_in[0]["name"],
            "output_channel": sel_out[0]["name"], "input_channels": [c.name for c in chans["u"]],
            "output_channels": [c.name for c in chans["y"]]}
    return Record(stack(sel_in), stack(sel_out), fs, units, name or PurePath(str(source)).name, meta, chans)


# ============================================================================ bounds
class RecordTooLarge(RecordFileError):
    """A record file declares more than a bounded parse loads (:func:`check_bounds`): ``what`` (an array or
    variable of the file) holds ``size`` ``unit`` (``"samples"``, values of a signal or of another array,
    or ``"bytes"``, decompressed) and ``limit`` is the most, in the same unit. Raised from the headers."""

    def __init__(self, path, what: str, size: int, limit: int, unit: str, counted: bool = True):
        self.what, self.size, self.limit, self.unit = what, int(size), int(limit), unit
        if unit == "samples":
            n = self.size if counted else f"more than {self.limit}"  # counted: all of them, else up to the limit
            held = f"{what} holds {n} {'samples' if what in ('u', 'y', 'the array') else 'values'}"
            super().__init__(path, f"{held}; the limit is {self.limit}")
        else:
            super().__init__(path, f"decompressing {what} brings the file to {self.size} bytes; the limit is "
                                   f"{self.limit} bytes")


def check_bounds(data, filename: str, *, max_samples=None, max_bytes=None, source=None) -> None:
    """Refuse a record file that a parse would load too much of, from its headers and directory alone.

    max_samples: most samples of ``u`` and of ``y`` [samples], and most values of any other array the
    parser reads (``fs``, units, ``name``) [values]. max_bytes: most bytes the parser may decompress from
    the file, all arrays and variables together [bytes]. Either may be None (not checked).

    What is read, per format: ``.npz``: the zip directory (each member's declared size) and the
    ``.npy`` header of each member the parser reads (shape x item size), which must agree (else a
    :class:`RecordFileError`, the member is corrupt); ``.npy``: the header (rows = samples; its data
    must be in the file, as numpy allocates the declared size before reading it); MATLAB v5 ``.mat``:
    each variable's tag, class, dimensions and name (a compressed variable's first bytes only; its
    stream is then inflated, at most to its declared size, to check the cells and structs it nests
    against their declared element counts); HDF5 / MATLAB v7.3: the shape and item size of the
    datasets read (a chunked dataset may be compressed or never written, read as its fill value) and, for a
    chunked one, its stored chunks (HDF5 inflates each whole, at its chunk shape x item size); once those are
    within bounds, each stored deflate chunk is inflated (1 MiB at a time, discarded) at most to its chunk size, and
    a filter other than deflate, shuffle and fletcher32 is refused (``record_formats_lab.hdf5_chunk_check``: a
    :class:`RecordFileError`). ``.csv``: its data rows (lines holding something other than blanks, not starting
    with ``#``, less the header), counted in the bytes before parsing. UFF-58 and TDMS hold their samples
    uncompressed: the size of the upload bounds them.

    Raises :class:`RecordTooLarge` (a ``RecordFileError``) naming the array and the limit; a file whose
    headers cannot be read is left to the parser, which fails on the same headers without loading.
    """
    fname = PurePath(str(filename)).name
    src = fname if source is None else source
    ext = PurePath(fname).suffix.lower()
    fh = _binary(data)
    fh.seek(0)
    try:
        if ext == ".npz":
            _check_sizes(src, _npz_arrays(src, fh), max_samples, max_bytes)
        elif ext == ".npy":
            _check_sizes(src, _npy_arrays(src, fh, max_samples), max_samples, max_bytes)
        elif ext == ".mat" and not _is_hdf5_mat(fh):
            _check_sizes(src, _mat_arrays(src, fh, max_samples, max_bytes), max_samples, max_bytes)
        elif ext in (".h5", ".hdf5", ".mat"):
            from . import record_formats_lab as lab

            _check_sizes(src, lab.hdf5_arrays(fh), max_samples, max_bytes)
            try:  # the sizes are within bounds: the stored chunks are checked against them
                lab.hdf5_chunk_check(fh)
            except lab.LabFormatError as exc:
                raise RecordFileError(src, str(exc)) from None
        elif ext == ".csv" and max_samples is not None:
            _check_csv_rows(src, fh, max_samples)
    finally:
        fh.seek(0)


def _check_sizes(p, arrays, max_samples, max_bytes, total=0) -> int:
    """arrays: (name, values, decompressed bytes) of what the parser loads, as the headers declare them;
    total: bytes of arrays checked before. Returns the new total [bytes]."""
    for what, count, _ in arrays:
        if max_samples is not None and count > max_samples:
            raise RecordTooLarge(p, what, count, max_samples, "samples")
    total += sum(nbytes for _, _, nbytes in arrays)
    if max_bytes is not None and total > max_bytes:
        names = [what for what, _, nbytes in sorted(arrays, key=lambda a: -a[2]) if nbytes]  # the largest first
        shown = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
        raise RecordTooLarge(p, shown, total, max_bytes, "bytes")
    return total


#: most members of an .npz record (its arrays): the zip directory is read only when it declares at most this many
MAX_NPZ_MEMBERS = 1024


def _npz_arrays(p, fh) -> list:
    """(name, values, data bytes) of each member ``_read_npz`` reads; the directory and the headers agree."""
    try:
        zf = open_archive(fh, MAX_NPZ_MEMBERS)
    except ArchiveError as exc:  # a directory of more entries than a record holds: not a record
        raise RecordFileError(p, f"not an .npz record: {exc}") from None
    except NPY_READ_ERRORS:
        return []  # np.load refuses it too
    out = []
    with zf:
        members = zf.namelist()
        for key in ("u", "y", "fs", "units_u", "units_y", "name"):  # found as np.load's NpzFile finds them
            name = key if key in members else (f"{key}.npy" if f"{key}.npy" in members else None)
            if name is None:
                continue
            info = zf.getinfo(name)
            try:
                m = member(zf, info)
            except ArchiveError as exc:
                raise RecordFileError(p, str(exc)) from None
            except NPY_READ_ERRORS:
                continue  # np.load fails on the same header, before allocating
            if m is None:  # not a .npy member: np.load returns its bytes
                out.append((key, 1, info.file_size))
            elif not m.dtype.hasobject:  # an object array is refused without pickle before its data is read
                out.append((key, m.count, m.nbytes))
    return out


#: the start of a CSV line holding data (or the header): not blank, not a # comment
_CSV_ROW = re.compile(rb"(?:\A|(?<=[\r\n]))[ \t]*[^#\s]")


def _check_csv_rows(p, fh, max_samples) -> None:
    """RecordTooLarge when the CSV file holds more than ``max_samples`` data rows (the header line not counted),
    counted in its bytes: its lines when they are few enough, else its rows up to the first one over."""
    raw = fh.read()
    if max(raw.count(b"\n"), raw.count(b"\r")) <= max_samples:
        return
    for rows, _ in enumerate(_CSV_ROW.finditer(raw)):  # rows: data rows before this line (the header is row 0)
        if rows > max_samples:
            raise RecordTooLarge(p, "u", rows, max_samples, "samples", counted=False)


def _npy_arrays(p, fh, max_samples) -> list:
    """(the array, rows, 0) of a .npy file: its data is not compressed, but must be in the file."""
    try:
        head = npy_header(fh)
    except (ValueError, EOFError, OSError, NotImplementedError):
        return []  # np.load fails on the same header
    if head is None or head[1].hasobject:
        return []
    shape, dtype = head
    start = fh.tell()
    present = fh.seek(0, 2) - start
    nbytes = math.prod(shape) * dtype.itemsize
    arrays = [("the array", shape[0] if shape else 1, 0)]
    _check_sizes(p, arrays, max_samples, None)
    if nbytes > present:  # np.load would allocate the declared size, then find the data missing
        raise RecordFileError(p, f"truncated .npy file: its header says {nbytes} data bytes (shape {shape}, "
                                 f"dtype {dtype}), the file holds {present}")
    return arrays


# MATLAB v5 (``scipy.io.loadmat``): data element types and array classes of the MAT-file format
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED = 1, 5, 6, 14, 15
_MX_CELL, _MX_STRUCT, _MX_OBJECT, _MX_OPAQUE = 1, 2, 3, 17
#: inflated bytes read to find a compressed variable's tag, class, dimensions and name
_MAT_HEAD = 4096
#: most nesting of cells and structs walked (deeper: refused as corrupt)
_MAT_DEPTH = 64


class _MatCorrupt(ValueError):
    pass


def _mat_element(buf, pos, e):
    """(type, payload, next position) of the data element at ``pos`` (full or small format)."""
    if pos + 8 > len(buf):
        raise _MatCorrupt("truncated data element")
    w0, w1 = struct.unpack_from(e + "II", buf, pos)
    if w0 >> 16:  # small format: the byte count in the upper half of the first word, the data in the second
        n = w0 >> 16
        if n > 4:
            raise _MatCorrupt("bad small data element")
        return w0 & 0xFFFF, bytes(buf[pos + 4:pos + 4 + n]), pos + 8
    end = pos + 8 + w1
    if end > len(buf):
        raise _MatCorrupt("truncated data element")
    return w0, bytes(buf[pos + 8:end]), pos + 8 + ((w1 + 7) & ~7)


def _mat_header(buf, e):
    """(class, dims, name, position after the name) of the miMATRIX payload ``buf`` (``dims`` None for
    opaque objects, whose payload then starts at the returned position)."""
    mdtype, flags, pos = _mat_element(buf, 0, e)
    if mdtype != _MI_UINT32 or len(flags) < 4:
        raise _MatCorrupt("bad array flags")
    mc = struct.unpack_from(e + "I", flags)[0] & 0xFF
    if mc == _MX_OPAQUE:
        return mc, None, "", pos
    mdtype, dims, pos = _mat_element(buf, pos, e)
    if mdtype != _MI_INT32 or len(dims) % 4:
        raise _MatCorrupt("bad dimensions")
    _, name, pos = _mat_element(buf, pos, e)
    return mc, struct.unpack(f"{e}{len(dims) // 4}i", dims), name.decode("latin-1"), pos


def _mat_walk(buf, e, depth=0) -> None:
    """Check that each cell and struct nested in the miMATRIX payload ``buf`` holds its declared elements:
    scipy allocates an element array of the declared size before reading them (each takes >= 8 bytes)."""
    if depth > _MAT_DEPTH:
        raise _MatCorrupt(f"cells or structs nested deeper than {_MAT_DEPTH}")
    mc, dims, name, pos = _mat_header(buf, e)
    if mc == _MX_OPAQUE:
        for _ in range(3):
            _, _, pos = _mat_element(buf, pos, e)
        elements = 1
    elif mc in (_MX_CELL, _MX_STRUCT, _MX_OBJECT):
        if any(d < 0 for d in dims):
            raise _MatCorrupt("negative dimension")
        elements = math.prod(dims)
        if mc != _MX_CELL:
            if mc == _MX_OBJECT:
                _, _, pos = _mat_element(buf, pos, e)  # class name
            _, length, pos = _mat_element(buf, pos, e)
            _, names, pos = _mat_element(buf, pos, e)
            width = struct.unpack_from(e + "i", length.ljust(4, b"\0"))[0]
            elements *= len(names) // width if width > 0 else 0
        if elements * 8 > len(buf) - pos:
            raise _MatCorrupt(f"{name or 'a cell or struct'} declares {elements} elements in {len(buf) - pos} "
                              f"bytes")
    else:
        return
    for _ in range(elements):
        if pos + 8 > len(buf):
            raise _MatCorrupt("truncated cell or struct")
        mdtype, n = struct.unpack_from(e + "II", buf, pos)
        if mdtype != _MI_MATRIX or pos + 8 + n > len(buf):
            raise _MatCorrupt("bad cell or struct element")
        if n:
            _mat_walk(memoryview(buf)[pos + 8:pos + 8 + n], e, depth + 1)
        pos += 8 + n


def _inflate(fh, nbytes, cap, keep=True) -> tuple[int, bytes]:
    """(length, bytes) inflated from the next ``nbytes`` bytes of ``fh`` (a zlib stream), stopping past
    ``cap`` bytes [bytes]; without ``keep`` only the length is kept (in steps of at most 1 MiB)."""
    d = zlib.decompressobj()
    out = bytearray()
    size, left = 0, nbytes
    while size <= cap and not d.eof:
        chunk = d.unconsumed_tail
        if not chunk:
            chunk = fh.read(min(left, 1 << 16))
            left -= len(chunk)
            if not chunk:
                break
        got = d.decompress(chunk, min(cap + 1 - size, 1 << 20))
        size += len(got)
        if keep:
            out += got
    return size, bytes(out)


def _mat_arrays(p, fh, max_samples, max_bytes) -> list:
    """(variable, values, inflated bytes) of each variable of a MATLAB v5 file, from its tag and header;
    the variables are checked against the limits as they are found, before a compressed one is inflated."""
    head = fh.read(128)
    # scipy reads a file whose first four bytes hold a zero as MATLAB v4 (not compressed, no cells)
    if len(head) < 128 or 0 in head[:4] or head[124 + (head[126:127] == b"I")] != 1:
        return []
    e = "<" if head[126:128] == b"IM" else ">"
    out: list = []
    pos, total = 128, 0
    try:
        while True:
            fh.seek(pos)
            tag = fh.read(8)
            if len(tag) < 8:
                break
            mdtype, n = struct.unpack(e + "II", tag)
            if mdtype == _MI_COMPRESSED and n:
                first = _inflate(fh, n, 8 + _MAT_HEAD)[1]
                if len(first) < 8 or struct.unpack_from(e + "I", first)[0] != _MI_MATRIX:
                    break  # scipy stops reading there with an error
                declared = struct.unpack_from(e + "I", first, 4)[0]
                if not declared:
                    break  # an empty variable: scipy stops reading there with an error
                body = first[8:8 + declared]
            elif mdtype == _MI_MATRIX and n:
                declared, body = 0, fh.read(n)  # not compressed: the upload holds it
            else:
                break  # scipy stops reading there with an error
            mc, dims, name, _ = _mat_header(body, e)
            found = (name if name in ("u", "y") else f"variable {name!r}",
                     math.prod(dims) if dims and name in ("u", "y") else 0, declared)
            total = _check_sizes(p, [found], max_samples, max_bytes, total)
            out.append(found)
            nests = mc in (_MX_CELL, _MX_STRUCT, _MX_OBJECT, _MX_OPAQUE)
            if declared:  # the stream must not hold more than its tag declares: scipy reads what it holds
                fh.seek(pos + 8)
                size, body = _inflate(fh, n, 8 + declared, keep=nests)
                if size > 8 + declared:
                    raise _MatCorrupt(f"compressed variable {name!r} inflates to more than the {declared} "
                                      f"bytes its tag declares")
                body = body[8:]
            if nests:
                _mat_walk(body, e)
            pos += 8 + n
    except _MatCorrupt as exc:
        raise RecordFileError(p, f"corrupt or truncated MATLAB file ({exc})") from None
    return out


# ============================================================================ shared checks
def _strip_name(msg: str) -> str:
    return msg.split(": ", 1)[1] if ": " in msg else msg


def check_fs(p, fs) -> float:
    """``fs`` as a finite positive float, or :class:`RecordFileError` naming ``p``."""
    try:
        v = float(fs)
    except (TypeError, ValueError):
        raise RecordFileError(p, f"fs must be a number in Hz, got {fs!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise RecordFileError(p, f"fs must be a finite positive frequency in Hz, got {fs!r}")
    return v


def _reconcile_fs(p, file_fs, arg_fs, fs_default=None) -> float:
    if file_fs is None:
        if arg_fs is not None:
            return arg_fs
        if fs_default is not None:
            return fs_default
        raise NoSamplingFrequency(p, "the file holds no sampling frequency (no time column / fs variable); pass fs")
    if not math.isfinite(file_fs) or file_fs <= 0:
        raise RecordFileError(p, f"sampling frequency in the file must be finite and positive, got {file_fs!r}")
    if arg_fs is not None and abs(arg_fs - file_fs) > _FS_RTOL * file_fs:
        raise RecordFileError(p, f"fs given as {arg_fs:g} Hz but the file says {file_fs:g} Hz")
    return float(file_fs)


def _signal(p, arr, label: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype.kind not in "biuf":
        if a.dtype.kind == "c":
            raise RecordFileError(p, f"{label} is complex; a real signal is required")
        raise RecordFileError(p, f"{label} must be numeric, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if a.ndim != 1:
        sq = np.squeeze(a)
        if sq.ndim != 1:
            raise RecordFileError(p, f"{label} must be a 1-D signal, got shape {a.shape}")
        a = sq
    if a.size == 0:
        raise RecordFileError(p, f"{label} is empty")
    bad = ~np.isfinite(a)
    if bad.any() and not (gaps_allowed() and not np.isinf(a).any()):  # NaN: a gap, where the reader takes them
        raise RecordFileError(
            p, f"{label} holds {int(bad.sum())} NaN/inf value(s), first at sample {int(np.argmax(bad))}"
        )
    return a


def _scalar(p, value, label: str) -> float:
    a = np.asarray(value)
    if a.size != 1 or a.dtype.kind not in "biuf":
        raise RecordFileError(p, f"{label} must be a numeric scalar, got shape {a.shape} dtype {a.dtype}")
    return float(a.reshape(()))


def _string(value) -> str:
    a = np.asarray(value)
    if a.dtype.kind in "US":
        if a.size == 0:
            return ""
        return "".join(str(x) for x in a.ravel()) if a.ndim else str(a.item())
    if a.dtype.kind == "O" and a.size == 1:
        return str(a.item())
    return str(value)


def _make(p, u, y, fs, units, name, meta=None) -> Record:
    u = _signal(p, u, "u")
    if y is not None:
        y = _signal(p, y, "y")
        if y.size != u.size:
            raise RecordFileError(p, f"u has {u.size} samples but y has {y.size}; they must match")
    units = {k: normalize_unit(v, p) for k, v in units.items()}
    rec_meta = {"source": str(p)}
    rec_meta.update(meta or {})
    return Record(u, y, fs, units, name, rec_meta)


# ---------------------------------------------------------------------------- CSV
_CSV_COLS = {"u": "u", "y": "y", "time": "time", "t": "time"}


def _parse_header_cell(cell: str):
    cell = cell.strip().strip('"').strip("'").strip()
    unit = ""
    for o, c in (("[", "]"), ("(", ")")):
        if cell.endswith(c) and o in cell:
            i = cell.rindex(o)
            unit = cell[i + 1 : -1].strip()
            cell = cell[:i].strip()
            break
    return cell.lower(), unit


def _read_csv(p, fh, fs, name, fs_default) -> Record:
    raw = fh.read()
    if b"\x00" in raw:
        raise RecordFileError(p, "not a text CSV file (binary content)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise RecordFileError(p, f"not UTF-8 text (byte {exc.start})") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise RecordFileError(p, "empty CSV file (no header line)")
    hline_no, header = lines[0]
    delim = ";" if header.count(";") > header.count(",") else ("\t" if "\t" in header and "," not in header else ",")
    try:
        cells = next(csv.reader([header], delimiter=delim))
    except csv.Error as exc:
        raise RecordFileError(p, f"line {hline_no}: bad header ({exc})") from None
    cols: dict[str, int] = {}
    units: dict[str, str] = {}
    chan_cols: dict[str, list] = {"u": [], "y": []}  # several channels: columns 'u:NAME [unit]', 'y:NAME [unit]'
    for j, cell in enumerate(cells):
        key, unit = _parse_header_cell(cell)
        named = _CSV_CHANNEL.match(cell.strip().strip('"').strip("'").strip())
        if named:
            side, cname = named.group(1).lower(), named.group(2).strip()
            if cname in [c for c, _, _ in chan_cols[side]]:
                raise RecordFileError(p, f"column {side}:{cname} appears twice in the header")
            chan_cols[side].append((cname, j, unit))
            continue
        if key in _CSV_COLS:
            canon = _CSV_COLS[key]
            if canon in cols:
                raise RecordFileError(p, f"column {canon!r} appears twice in the header")
            cols[canon] = j
            if unit:
                units[canon] = unit
    for side in ("u", "y"):
        if chan_cols[side] and side in cols:
            raise RecordFileError(p, f"the header has both a column {side!r} and named {side} channels "
                                     f"({side}:NAME); use one or the other")
        if len(chan_cols[side]) > MAX_CHANNELS:
            raise RecordFileError(p, f"{len(chan_cols[side])} {side} channels; at most {MAX_CHANNELS} are read")
    if "u" not in cols and not chan_cols["u"]:
        raise RecordFileError(
            p, f"missing column 'u' (header names {', '.join(repr(c.strip()) for c in cells)}; expected time,u,y)"
        )
    ncol = len(cells)
    data = np.empty((len(lines) - 1, ncol))
    # a gap (model.gaps; where the reader takes them): 'nan' or an empty cell in a column other than time
    gap_cols = {j for k, j in cols.items() if k != "time"} if gaps_allowed() else set()
    if gaps_allowed():
        gap_cols |= {j for side in chan_cols.values() for _, j, _ in side}
    for r, (line_no, ln) in enumerate(lines[1:]):
        try:
            row = next(csv.reader([ln], delimiter=delim))
        except csv.Error as exc:
            raise RecordFileError(p, f"line {line_no}: {exc}") from None
        if len(row) != ncol:
            raise RecordFileError(p, f"line {line_no}: {len(row)} fields, the header has {ncol}")
        for j, cell in enumerate(row):
            s = cell.strip()
            if j in gap_cols and s == "":
                s = "nan"
            try:
                v = float(s)
            except ValueError:
                raise RecordFileError(p, f"line {line_no}: {s[:30]!r} is not a number") from None
            if not math.isfinite(v) and not (j in gap_cols and math.isnan(v)):
                col = next((k for k, c in cols.items() if c == j), f"column {j + 1}")
                raise RecordFileError(p, f"line {line_no}: {col} is {s[:30]!r} (NaN/inf not allowed)")
            data[r, j] = v
    if data.shape[0] == 0:
        raise RecordFileError(p, "no data rows after the header")
    file_fs = None
    if "time" in cols:
        t = data[:, cols["time"]]
        if t.size < 2:
            raise RecordFileError(p, "a time column needs at least 2 rows to give the sampling frequency")
        dt = np.diff(t)
        mean_dt = (t[-1] - t[0]) / (t.size - 1)
        if not mean_dt > 0:
            raise RecordFileError(p, "time column is not increasing")
        worst = int(np.argmax(np.abs(dt - mean_dt)))
        if abs(dt[worst] - mean_dt) > 0.01 * mean_dt:
            raise RecordFileError(
                p, f"time step is not uniform: step {dt[worst]:g} s at row {worst + 2} vs mean {mean_dt:g} s"
            )
        file_fs = float(f"{1.0 / mean_dt:.10g}")
    fs = _reconcile_fs(p, file_fs, fs, fs_default)
    if chan_cols["u"] or chan_cols["y"]:
        return _csv_channels(p, data, cols, units, chan_cols, fs, name)
    u = data[:, cols["u"]]
    y = data[:, cols["y"]] if "y" in cols else None
    return _make(p, u, y, fs, {"u": units.get("u", ""), "y": units.get("y", "")}, name)


#: a CSV header cell naming one channel: ``u:NAME`` or ``y:NAME``, optionally followed by ``[unit]`` / ``(unit)``
_CSV_CHANNEL = re.compile(r"^([uUyY])\s*:\s*([^\[\]()]*?[^\s\[\]()])\s*(?:[\[(][^\])]*[\])])?$")


def _csv_channels(p, data, cols, units, chan_cols, fs, name) -> Record:
    """A CSV record whose header names channels (``u:NAME [unit]``, ``y:NAME [unit]``; a plain ``u`` or ``y``
    column is that side's one channel)."""
    sig, chans = {}, {}
    for side in ("u", "y"):
        entries = chan_cols[side] or ([(side, cols[side], units.get(side, ""))] if side in cols else [])
        if not entries:
            continue
        chans[side] = [Channel(c, normalize_unit(unit, p)) for c, _, unit in entries]
        block = data[:, [j for _, j, _ in entries]]
        sig[side] = block[:, 0] if block.shape[1] == 1 else block
    common = {k: (v[0].unit if len({c.unit for c in v}) == 1 else "") for k, v in chans.items()}
    common.setdefault("y", "")
    try:
        return Record(sig["u"], sig.get("y"), fs, common, name, {"source": str(p)}, chans)
    except RecordError as exc:
        raise RecordFileError(p, _strip_name(str(exc))) from None


# ---------------------------------------------------------------------------- NPZ / NPY
def _read_npz(p, fh, fs, name, stem) -> Record:
    if not zipfile.is_zipfile(fh):
        raise RecordFileError(p, "not a valid .npz file (not a zip archive; corrupt or truncated?)")
    fh.seek(0)
    with np.load(fh, allow_pickle=False) as z:
        keys = set(z.files)
        if "u" not in keys:
            raise RecordFileError(p, f"missing array 'u' (arrays in file: {', '.join(sorted(keys)) or 'none'})")
        u = z["u"]
        y = z["y"] if "y" in keys else None
        file_fs = _scalar(p, z["fs"], "fs") if "fs" in keys else None
        if "channels_u" in keys or "channels_y" in keys:  # several channels, named
            fs = _reconcile_fs(p, file_fs, fs)
            fname = _string(z["name"]) if "name" in keys else None
            return _npz_channels(p, z, keys, u, y, fs, name or fname or stem)
        units = {"u": _string(z["units_u"]) if "units_u" in keys else "",
                 "y": _string(z["units_y"]) if "units_y" in keys else ""}
        fname = _string(z["name"]) if "name" in keys else None
    fs = _reconcile_fs(p, file_fs, fs)
    return _make(p, u, y, fs, units, name or fname or stem)


def _strings(p, z, key: str, k: int, what: str) -> list[str]:
    """A string array of the .npz (k entries; a scalar string applies to all k)."""
    a = np.asarray(z[key])
    if a.dtype.kind not in "US":
        raise RecordFileError(p, f"{key} must hold strings, got dtype {a.dtype}")
    vals = [str(a.item())] * k if a.ndim == 0 else [str(x) for x in a.ravel()]
    if len(vals) != k:
        raise RecordFileError(p, f"{key} names {len(vals)} {what} but the signal has {k} channel(s)")
    return vals


def _npz_channels(p, z, keys, u, y, fs, name) -> Record:
    """A .npz record with named channels: ``u`` (n,) or (n, n_inputs) with ``channels_u`` (one name per column),
    ``y`` likewise with ``channels_y``; ``units_u`` / ``units_y`` one unit per channel (or one for all)."""
    chans, sig = {}, {}
    for key, arr in (("u", u), ("y", y)):
        if arr is None:
            continue
        a = np.asarray(arr)
        if a.ndim == 2 and a.shape[1] > MAX_CHANNELS:
            raise RecordFileError(p, f"{key} has {a.shape[1]} channels; at most {MAX_CHANNELS} are read")
        if a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        if a.ndim not in (1, 2):
            raise RecordFileError(p, f"{key} must be (n,) or (n, channels), got shape {a.shape}")
        cols = [a] if a.ndim == 1 else [a[:, j] for j in range(a.shape[1])]
        cols = [_signal(p, c, key if a.ndim == 1 else f"{key}[:, {j}]") for j, c in enumerate(cols)]
        k = len(cols)
        names = _strings(p, z, f"channels_{key}", k, "channels") if f"channels_{key}" in keys else (
            [key] if k == 1 else [f"{key}{j}" for j in range(k)])
        units = _strings(p, z, f"units_{key}", k, "units") if f"units_{key}" in keys else [""] * k
        chans[key] = [Channel(nm, normalize_unit(un, p)) for nm, un in zip(names, units)]
        sig[key] = cols[0] if k == 1 else np.column_stack(cols)
    if "y" in sig and sig["y"].shape[0] != sig["u"].shape[0]:
        raise RecordFileError(p, f"u has {sig['u'].shape[0]} samples but y has {sig['y'].shape[0]}; they must match")
    units = {k: (v[0].unit if len({c.unit for c in v}) == 1 else "") for k, v in chans.items()}
    units.setdefault("y", "")
    try:
        return Record(sig["u"], sig.get("y"), fs, units, name, {"source": str(p)}, chans)
    except RecordError as exc:
        raise RecordFileError(p, _strip_name(str(exc))) from None


def _read_npy(p, fh, fs, name, fs_default) -> Record:
    arr = np.load(fh, allow_pickle=False)
    file_fs = None
    if arr.dtype.names:
        fields = set(arr.dtype.names)
        if "u" not in fields:
            raise RecordFileError(p, f"missing field 'u' (fields: {', '.join(arr.dtype.names)})")
        u = arr["u"]
        y = arr["y"] if "y" in fields else None
        tkey = "time" if "time" in fields else ("t" if "t" in fields else None)
        if tkey:
            t = np.asarray(arr[tkey], dtype=float).ravel()
            if t.size >= 2 and np.all(np.isfinite(t)) and t[-1] > t[0]:
                file_fs = float(f"{(t.size - 1) / (t[-1] - t[0]):.10g}")
    else:
        if arr.dtype.kind not in "biuf":
            raise RecordFileError(p, f"array must be numeric, got dtype {arr.dtype}")
        if arr.ndim == 1 or (arr.ndim == 2 and arr.shape[1] == 1):
            u, y = arr.reshape(-1), None
        elif arr.ndim == 2 and arr.shape[1] == 2:
            u, y = arr[:, 0], arr[:, 1]
        else:
            raise RecordFileError(p, f"wrong shape {arr.shape}: expected (n, 2) with columns u, y, or (n,) for u")
    fs = _reconcile_fs(p, file_fs, fs, fs_default)
    return _make(p, u, y, fs, {"u": "", "y": ""}, name)


# ---------------------------------------------------------------------------- MAT
def _loadmat(p, fh) -> dict:
    import scipy.io

    head = fh.read(128)
    if len(head) < 128:
        raise RecordFileError(p, f"truncated or not a MATLAB file ({len(head)} bytes)")
    if head[:19] == b"MATLAB 7.3 MAT-file" or head[:8] == b"\x89HDF\r\n\x1a\n":
        raise RecordFileError(p, "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or -v6")
    fh.seek(0)
    try:
        return scipy.io.loadmat(fh, squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise RecordFileError(p, "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or -v6") from None
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(p, f"corrupt or truncated MATLAB file ({type(exc).__name__}: {exc})") from None


def _read_lab(p, fh, ext, fs, name) -> Record:
    """UFF-58, TDMS, HDF5 or MATLAB v7.3 (``storage.record_formats_lab``)."""
    from . import record_formats_lab as lab

    reader = {".uff": lab.read_uff, ".unv": lab.read_uff, ".tdms": lab.read_tdms, ".h5": lab.read_hdf5,
              ".hdf5": lab.read_hdf5, ".mat": lab.read_hdf5}[ext]
    try:
        got = reader(p, fh)
    except lab.LabFormatError as exc:
        raise RecordFileError(p, str(exc)) from None
    fs = _reconcile_fs(p, got["fs"], fs)
    units, meta = {}, dict(got["meta"])
    for k, label in got["units"].items():  # lab software spells units its own way: unknown = not stated
        try:
            units[k] = normalize_unit(label, p)
        except RecordFileError:
            units[k] = ""
            meta[f"{k}_unit_label"] = label
    return _make(p, got["u"], got["y"], fs, units, name, meta)


def _is_hdf5_mat(fh) -> bool:
    head = fh.read(128)
    fh.seek(0)
    return head[:19] == b"MATLAB 7.3 MAT-file" or head[:8] == b"\x89HDF\r\n\x1a\n"


def _read_mat(p, fh, fs, name) -> Record:
    if _is_hdf5_mat(fh):  # saved with -v7.3: an HDF5 file (h5py, extra formats)
        return _read_lab(p, fh, ".mat", fs, name)
    d = _loadmat(p, fh)
    keys = {k for k in d if not k.startswith("__")}
    if "u" not in keys:
        lms = [k for k in keys if hasattr(d[k], "_fieldnames") and "y_values" in d[k]._fieldnames]
        hint = f" (LMS structs {', '.join(sorted(lms))}: pass the export folder instead)" if lms else ""
        raise RecordFileError(p, f"missing variable 'u' (variables: {', '.join(sorted(keys)) or 'none'}){hint}")
    file_fs = _scalar(p, d["fs"], "fs") if "fs" in keys else None
    fs = _reconcile_fs(p, file_fs, fs)
    units = {"u": _string(d["units_u"]) if "units_u" in keys else "",
             "y": _string(d["units_y"]) if "units_y" in keys else ""}
    return _make(p, d["u"], d.get("y"), fs, units, name)


# ---------------------------------------------------------------------------- LMS Test.Lab
def _field(p, s, dotted: str):
    cur = s
    for part in dotted.split("."):
        if not hasattr(cur, "_fieldnames") or part not in cur._fieldnames:
            raise RecordFileError(p, f"LMS struct has no field {dotted!r}")
        cur = getattr(cur, part)
    return cur


def _lms_channel(p, fh, struct_name: str) -> dict:
    d = _loadmat(p, fh)
    if struct_name not in d:
        names = sorted(k for k in d if not k.startswith("__"))
        raise RecordFileError(p, f"missing LMS struct {struct_name!r} (variables: {', '.join(names) or 'none'})")
    s = d[struct_name]
    inc = _scalar(p, _field(p, s, "x_values.increment"), "x_values.increment")
    if not math.isfinite(inc) or inc <= 0:
        raise RecordFileError(p, f"x_values.increment must be a positive sample period in s, got {inc!r}")
    nval = _scalar(p, _field(p, s, "x_values.number_of_values"), "x_values.number_of_values")
    values = np.asarray(_field(p, s, "y_values.values"))
    label = _string(_field(p, s, "y_values.quantity.label"))
    factor, offset = 1.0, 0.0
    try:
        ut = _field(p, s, "y_values.quantity.unit_transformation")
        factor = float(getattr(ut, "factor", 1.0))
        offset = float(getattr(ut, "offset", 0.0))
    except (RecordFileError, TypeError, ValueError):
        pass
    if values.ndim != 1:
        raise RecordFileError(p, f"{struct_name}.y_values.values must be one channel (1-D), got shape {values.shape}")
    if values.size != int(nval):
        raise RecordFileError(
            p, f"{struct_name} has {values.size} values but x_values.number_of_values says {int(nval)} (truncated?)"
        )
    sig = _signal(p, values, f"{struct_name}.y_values.values")
    if factor != 1.0 or offset != 0.0:
        sig = sig * factor + offset
    meta = {}
    try:
        fr = s.function_record
        meta["channel"] = _string(fr.primary_channel.label)
        meta["creation_time"] = _string(fr.creation_time)
        meta["run_name"] = _string(fr.TL_export_properties_annotation.run_name)
    except AttributeError:
        pass
    return {"values": sig, "increment": inc, "unit": normalize_unit(label, p), "meta": meta}
