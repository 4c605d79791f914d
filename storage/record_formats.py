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

``source`` names the file in every error message and in ``Record.meta["source"]`` (default: the
file name). Every problem raises :class:`RecordFileError` (a ``ValueError``) with one line naming
the source and the problem.
"""
from __future__ import annotations

import csv
import io
import math
import zipfile
from pathlib import PurePath

import numpy as np

from gpnarx.model.record import Record, RecordError

from .record_formats_lab import LAB_FORMATS

__all__ = [
    "RecordFileError",
    "NoSamplingFrequency",
    "KNOWN_UNITS",
    "FORMATS",
    "LMS_INPUT",
    "LMS_OUTPUT",
    "normalize_unit",
    "check_fs",
    "parse_record",
    "parse_lms",
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


def parse_record(data, filename: str, *, fs=None, name=None, fs_default=None, source=None) -> Record:
    """Parse the contents of a record file into a :class:`Record`.

    data: bytes or a seekable binary file. filename: its name; the extension picks the format
    (``FORMATS``). fs: sampling frequency [Hz]; required when the file
    has none, checked against the file's otherwise (0.1 %). fs_default: used only when the file
    carries no sampling information. name: record name (default: the file name's stem).
    source: what error messages and ``meta["source"]`` call the file (default: ``filename``).
    An LMS export needs both of its files: :func:`parse_lms`.
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
              time_source=None) -> Record:
    """Parse an LMS Test.Lab export from the contents of its two files (see ``storage.record_files``).

    shaker: ``TimeShaker.mat`` (input u, struct ``Time_Shaker__X``); time: ``Time.mat`` (output y,
    struct ``Time_Laser__X``); each bytes or a seekable binary file. source names the export in
    messages and ``meta["source"]``; shaker_source / time_source name the two files (default
    ``SOURCE/TimeShaker.mat`` and ``SOURCE/Time.mat``). name: record name (default: source's name).
    """
    if fs is not None:
        fs = check_fs(source, fs)
    pin = shaker_source if shaker_source is not None else f"{source}/{LMS_INPUT[0]}"
    pout = time_source if time_source is not None else f"{source}/{LMS_OUTPUT[0]}"
    try:
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
    if bad.any():
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
    for j, cell in enumerate(cells):
        key, unit = _parse_header_cell(cell)
        if key in _CSV_COLS:
            canon = _CSV_COLS[key]
            if canon in cols:
                raise RecordFileError(p, f"column {canon!r} appears twice in the header")
            cols[canon] = j
            if unit:
                units[canon] = unit
    if "u" not in cols:
        raise RecordFileError(
            p, f"missing column 'u' (header names {', '.join(repr(c.strip()) for c in cells)}; expected time,u,y)"
        )
    ncol = len(cells)
    data = np.empty((len(lines) - 1, ncol))
    for r, (line_no, ln) in enumerate(lines[1:]):
        try:
            row = next(csv.reader([ln], delimiter=delim))
        except csv.Error as exc:
            raise RecordFileError(p, f"line {line_no}: {exc}") from None
        if len(row) != ncol:
            raise RecordFileError(p, f"line {line_no}: {len(row)} fields, the header has {ncol}")
        for j, cell in enumerate(row):
            s = cell.strip()
            try:
                v = float(s)
            except ValueError:
                raise RecordFileError(p, f"line {line_no}: {s[:30]!r} is not a number") from None
            if not math.isfinite(v):
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
    u = data[:, cols["u"]]
    y = data[:, cols["y"]] if "y" in cols else None
    return _make(p, u, y, fs, {"u": units.get("u", ""), "y": units.get("y", "")}, name)


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
        units = {"u": _string(z["units_u"]) if "units_u" in keys else "",
                 "y": _string(z["units_y"]) if "units_y" in keys else ""}
        fname = _string(z["name"]) if "name" in keys else None
    fs = _reconcile_fs(p, file_fs, fs)
    return _make(p, u, y, fs, units, name or fname or stem)


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
