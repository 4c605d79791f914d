"""Record readers and writers (CSV, NPZ, NPY, MATLAB .mat, LMS Test.Lab exports) and
frequency-domain integration / differentiation of measured velocities.

Reading
-------
``read_record(path, fs=None, name=None)`` returns a :class:`model.records.Record` and dispatches on
the path:

- ``.csv``: a header line names the columns (case-insensitive, in any order): ``u`` (required),
  ``y`` (optional) and ``time`` (or ``t``) [s]. A unit may follow a column name in brackets or
  parentheses (``u [N]``, ``y (m/s)``). With a ``time`` column the sampling frequency is derived
  from the time step, which must be uniform (every step within 1 % of the mean step); without one,
  ``fs`` must be given. Lines starting with ``#`` and blank lines are skipped.
- ``.npz``: arrays ``u`` (required) and ``y`` (optional), scalar ``fs`` [Hz] (or the ``fs``
  argument), optional strings ``units_u``, ``units_y`` and ``name``. Loaded without pickle.
- ``.npy``: a 2-D array with columns ``u, y`` (``(n, 2)``) or ``u`` only (``(n,)`` or ``(n, 1)``),
  or a structured array with fields ``u``, optional ``y`` and ``time``; ``fs`` must be given unless
  there is a ``time`` field. Loaded without pickle.
- ``.mat`` (MATLAB v5, ``scipy.io.loadmat``): variables ``u``, optional ``y``, ``fs`` (or the
  argument), optional strings ``units_u``, ``units_y``. A ``Time.mat``/``TimeShaker.mat`` file of an
  LMS export is read as its folder (below).
- a folder holding ``Time.mat`` and ``TimeShaker.mat`` (LMS Test.Lab MATLAB export, as in the
  UNESP-BERT records): input ``u`` is the struct ``Time_Shaker__X`` of ``TimeShaker.mat`` (shaker
  amplifier voltage, ``V``), output ``y`` the struct ``Time_Laser__X`` of ``Time.mat`` (free-end
  velocity, ``m/s``). From each struct the reader takes ``x_values.increment`` (sample period [s]),
  ``x_values.number_of_values``, ``y_values.values`` and the unit label
  ``y_values.quantity.label``; all of them are read from the files, nothing is assumed. Test.Lab
  saves the values in MKS units and describes the labelled (display) unit by
  ``y_values.quantity.unit_transformation`` (``display = factor * value + offset``); the reader
  applies that transformation so the samples are in the labelled unit (factor 1 and offset 0 for
  the laser and shaker channels). ``Record.meta`` keeps the channel labels, the run name and the
  creation time.

``fs`` given as an argument must agree (0.1 %) with any fs stored in the file. ``fs_default`` is
used only when the file carries no sampling information (CSV without time, NPY).

Units: the labels must belong to :data:`KNOWN_UNITS` (after normalising spellings such as
``m/s²``/``m/s2`` to ``m/s^2``); an empty label means "not stated".

Every problem (missing file, unsupported extension, missing column/variable, wrong shape, NaN/inf,
unknown unit, corrupt or truncated file, inconsistent fs) raises :class:`RecordFileError` (a
``ValueError``) with one line naming the file and the problem.

Writing
-------
``write_record(path, record)`` writes ``.npz`` (``u``, ``y`` float64 1-D, scalar ``fs``, ``units_u``,
``units_y``, ``name``), ``.csv`` (header ``time,u,y``, 17 significant digits) or ``.mat``
(``u``, ``y``, ``fs``, ``units_u``, ``units_y``). Writes are atomic: the data goes to a temporary
file in the destination folder which is then renamed over the destination with ``os.replace``;
on any error the temporary file is removed and an existing destination is left untouched.

Integration / differentiation
-----------------------------
``velocity_to_displacement`` and ``velocity_to_acceleration`` work in the frequency domain; see
their docstrings.
"""
from __future__ import annotations

import csv
import io
import math
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from gpnarx.model.records import Record, RecordError

__all__ = [
    "RecordFileError",
    "KNOWN_UNITS",
    "normalize_unit",
    "read_record",
    "write_record",
    "read_lms",
    "is_lms_folder",
    "velocity_to_displacement",
    "velocity_to_acceleration",
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

_LMS_INPUT = ("TimeShaker.mat", "Time_Shaker__X")
_LMS_OUTPUT = ("Time.mat", "Time_Laser__X")
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


# ============================================================================ reading
def read_record(path, fs=None, name=None, fs_default=None) -> Record:
    """Read a record file or LMS folder (see the module docstring) into a :class:`Record`.

    path: file or folder. fs: sampling frequency [Hz]; required when the file has none, checked
    against the file's otherwise. name: record name (default: the file or folder stem).
    fs_default: used only when the file carries no sampling information.
    """
    p = Path(os.fspath(path)).expanduser()
    if fs is not None:
        fs = _check_fs_arg(p, fs)
    if fs_default is not None and fs is None:
        fs_default = _check_fs_arg(p, fs_default)
    if not p.exists():
        raise RecordFileError(p, "no such file or folder")
    try:
        if p.is_dir():
            if is_lms_folder(p):
                return read_lms(p, fs=fs, name=name)
            raise RecordFileError(
                p, "folder is not an LMS Test.Lab export (expected Time.mat and TimeShaker.mat in it)"
            )
        ext = p.suffix.lower()
        if ext == ".csv":
            return _read_csv(p, fs, name, fs_default)
        if ext == ".npz":
            return _read_npz(p, fs, name)
        if ext == ".npy":
            return _read_npy(p, fs, name, fs_default)
        if ext == ".mat":
            if p.name in (_LMS_INPUT[0], _LMS_OUTPUT[0]) and is_lms_folder(p.parent):
                return read_lms(p.parent, fs=fs, name=name)
            return _read_mat(p, fs, name)
        raise RecordFileError(
            p, f"unsupported record format {p.suffix or '(no extension)'!r}; use .csv, .npz, .npy, .mat or an LMS folder"
        )
    except RecordFileError:
        raise
    except RecordError as exc:  # Record validation (NaN, shapes, fs)
        raise RecordFileError(p, _strip_name(str(exc))) from None
    except MemoryError:
        raise RecordFileError(p, "file too large to load") from None
    except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
        raise RecordFileError(p, f"cannot read the file ({type(exc).__name__}: {exc})") from None


def _strip_name(msg: str) -> str:
    return msg.split(": ", 1)[1] if ": " in msg else msg


def _check_fs_arg(p, fs) -> float:
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
        raise RecordFileError(p, "the file holds no sampling frequency (no time column / fs variable); pass fs")
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
    return Record(u, y, fs, units, name or _stem(p), rec_meta)


def _stem(p: Path) -> str:
    return p.name if p.is_dir() else p.stem


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


def _read_csv(p: Path, fs, name, fs_default) -> Record:
    raw = p.read_bytes()
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
def _read_npz(p: Path, fs, name) -> Record:
    if not zipfile.is_zipfile(p):
        raise RecordFileError(p, "not a valid .npz file (not a zip archive; corrupt or truncated?)")
    with np.load(p, allow_pickle=False) as z:
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
    return _make(p, u, y, fs, units, name or fname)


def _read_npy(p: Path, fs, name, fs_default) -> Record:
    arr = np.load(p, allow_pickle=False)
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
def _loadmat(p: Path) -> dict:
    import scipy.io

    with open(p, "rb") as fh:
        head = fh.read(128)
    if len(head) < 128:
        raise RecordFileError(p, f"truncated or not a MATLAB file ({len(head)} bytes)")
    if head[:19] == b"MATLAB 7.3 MAT-file" or head[:8] == b"\x89HDF\r\n\x1a\n":
        raise RecordFileError(p, "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or -v6")
    try:
        return scipy.io.loadmat(p, squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise RecordFileError(p, "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or -v6") from None
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(p, f"corrupt or truncated MATLAB file ({type(exc).__name__}: {exc})") from None


def _read_mat(p: Path, fs, name) -> Record:
    d = _loadmat(p)
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
def is_lms_folder(path) -> bool:
    """True when ``path`` is a folder holding ``Time.mat`` and ``TimeShaker.mat``."""
    p = Path(path)
    return p.is_dir() and (p / _LMS_INPUT[0]).is_file() and (p / _LMS_OUTPUT[0]).is_file()


def _field(p, s, dotted: str):
    cur = s
    for part in dotted.split("."):
        if not hasattr(cur, "_fieldnames") or part not in cur._fieldnames:
            raise RecordFileError(p, f"LMS struct has no field {dotted!r}")
        cur = getattr(cur, part)
    return cur


def _lms_channel(p: Path, struct_name: str) -> dict:
    d = _loadmat(p)
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


def read_lms(folder, fs=None, name=None) -> Record:
    """Read an LMS Test.Lab export folder: u = shaker voltage, y = laser velocity (see module doc)."""
    folder = Path(folder)
    pin = folder / _LMS_INPUT[0]
    pout = folder / _LMS_OUTPUT[0]
    for f in (pin, pout):
        if not f.is_file():
            raise RecordFileError(folder, f"LMS export folder lacks {f.name}")
    try:
        cin = _lms_channel(pin, _LMS_INPUT[1])
        cout = _lms_channel(pout, _LMS_OUTPUT[1])
    except RecordFileError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(folder, f"cannot read the LMS export ({type(exc).__name__}: {exc})") from None
    if abs(cin["increment"] - cout["increment"]) > 1e-9 * cin["increment"]:
        raise RecordFileError(
            folder, f"sample periods differ: TimeShaker.mat {cin['increment']:g} s, Time.mat {cout['increment']:g} s"
        )
    if cin["values"].size != cout["values"].size:
        raise RecordFileError(
            folder, f"TimeShaker.mat has {cin['values'].size} samples but Time.mat has {cout['values'].size}"
        )
    file_fs = float(f"{1.0 / cin['increment']:.12g}")
    fs = _reconcile_fs(folder, file_fs, fs)
    meta = {
        "format": "lms-testlab",
        "input_channel": cin["meta"].get("channel", ""),
        "output_channel": cout["meta"].get("channel", ""),
        "run_name": cout["meta"].get("run_name", ""),
        "creation_time": cout["meta"].get("creation_time", ""),
    }
    return _make(folder, cin["values"], cout["values"], fs, {"u": cin["unit"], "y": cout["unit"]},
                 name or folder.name, meta)


# ============================================================================ writing
def write_record(path, record: Record) -> Path:
    """Write ``record`` to ``path`` (.npz, .csv or .mat) atomically; returns the path."""
    p = Path(os.fspath(path)).expanduser()
    ext = p.suffix.lower()
    if ext not in (".npz", ".csv", ".mat"):
        raise RecordFileError(p, f"cannot write format {p.suffix or '(no extension)'!r}; use .npz, .csv or .mat")
    if not isinstance(record, Record):
        raise RecordFileError(p, f"expected a Record, got {type(record).__name__}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise RecordFileError(p, f"folder {parent} does not exist")
    u = np.ascontiguousarray(record.u, dtype=np.float64)
    y = None if record.y is None else np.ascontiguousarray(record.y, dtype=np.float64)
    units = {k: normalize_unit(record.units.get(k, ""), p) for k in ("u", "y")}
    tmp_name = None
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=parent)
        with os.fdopen(fd, "wb") as fh:
            if ext == ".npz":
                arrays = {"u": u, "fs": np.float64(record.fs), "units_u": np.str_(units["u"]),
                          "units_y": np.str_(units["y"]), "name": np.str_(record.name)}
                if y is not None:
                    arrays["y"] = y
                np.savez(fh, **arrays)
            elif ext == ".csv":
                buf = io.StringIO()
                t = np.arange(u.size) / record.fs
                if y is None:
                    buf.write("time,u\n")
                    for row in zip(t, u):
                        buf.write("%.17g,%.17g\n" % row)
                else:
                    buf.write("time,u,y\n")
                    for row in zip(t, u, y):
                        buf.write("%.17g,%.17g,%.17g\n" % row)
                fh.write(buf.getvalue().encode("utf-8"))
            else:
                import scipy.io

                mdict = {"u": u, "fs": float(record.fs), "units_u": units["u"], "units_y": units["y"]}
                if y is not None:
                    mdict["y"] = y
                scipy.io.savemat(fh, mdict, do_compression=False)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, p)
        tmp_name = None
    except RecordFileError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(p, f"cannot write the record ({type(exc).__name__}: {exc})") from None
    finally:
        if tmp_name is not None:
            try:
                os.unlink(tmp_name)
            except OSError:
                pass
    return p


# ============================================================================ integration
def _hp_weight(f: np.ndarray, f_highpass: float) -> np.ndarray:
    """0 below f_hp/2, raised-cosine taper from f_hp/2 to f_hp, 1 above."""
    w = np.ones_like(f)
    if f_highpass <= 0:
        w[f == 0] = 0.0
        return w
    lo = 0.5 * f_highpass
    w[f <= lo] = 0.0
    band = (f > lo) & (f < f_highpass)
    w[band] = 0.5 - 0.5 * np.cos(np.pi * (f[band] - lo) / (f_highpass - lo))
    return w


def velocity_to_displacement(v, fs: float, f_highpass: float = 2.0, periodic: bool = False) -> np.ndarray:
    """Drift-free displacement [m] from a velocity signal [m/s] sampled at ``fs`` [Hz].

    Frequency-domain integration: the mean is removed, the signal is zero-padded to at least twice
    its length (unless ``periodic``, when the record is taken as one period and not padded), its
    FFT is divided by ``j 2 pi f`` and multiplied by a high-pass weight that is 0 below
    ``f_highpass / 2``, rises as a raised cosine to 1 at ``f_highpass`` [Hz] and is 1 above (the
    DC bin is always 0). This removes the drift that time-domain integration of sensor offset and
    low-frequency noise produces. Content below ``f_highpass`` is lost (default 2 Hz, well under
    the 18.8 Hz first mode of BERT and the 5 Hz lower sweep limit of the Bouc-Wen protocol); the
    first and last ``~1 / f_highpass`` seconds of a non-periodic record are less accurate.
    """
    x = np.asarray(v, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"v must be a non-empty 1-D signal, got shape {x.shape}")
    fs = float(fs)
    if not math.isfinite(fs) or fs <= 0:
        raise ValueError(f"fs must be a positive frequency in Hz, got {fs}")
    n = x.size
    x = x - x.mean()
    nfft = n if periodic else _next_len(2 * n)
    spec = np.fft.rfft(x, nfft)
    f = np.fft.rfftfreq(nfft, 1.0 / fs)
    w = _hp_weight(f, float(f_highpass))
    out = np.zeros_like(spec)
    nz = f > 0
    out[nz] = spec[nz] * w[nz] / (2j * np.pi * f[nz])
    if nfft % 2 == 0:
        out[-1] = 0.0  # Nyquist bin of an even length: no phase information
    return np.fft.irfft(out, nfft)[:n]


def velocity_to_acceleration(v, fs: float, periodic: bool = False) -> np.ndarray:
    """Acceleration [m/s^2] from a velocity signal [m/s] sampled at ``fs`` [Hz].

    Frequency-domain differentiation: the FFT is multiplied by ``j 2 pi f`` (DC and an even-length
    Nyquist bin set to 0). Unless ``periodic``, the signal is first extended by its mirror image so
    that the transformed sequence has no jump at the wrap-around (no Gibbs ringing at the ends).
    """
    x = np.asarray(v, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"v must be a non-empty 1-D signal, got shape {x.shape}")
    fs = float(fs)
    if not math.isfinite(fs) or fs <= 0:
        raise ValueError(f"fs must be a positive frequency in Hz, got {fs}")
    n = x.size
    ext = x if periodic else np.concatenate([x, x[::-1]])
    m = ext.size
    spec = np.fft.rfft(ext)
    f = np.fft.rfftfreq(m, 1.0 / fs)
    spec = spec * (2j * np.pi * f)
    spec[0] = 0.0
    if m % 2 == 0:
        spec[-1] = 0.0
    return np.fft.irfft(spec, m)[:n]


def _next_len(n: int) -> int:
    try:
        from scipy.fft import next_fast_len

        return int(next_fast_len(n, real=True))
    except Exception:  # noqa: BLE001
        return 1 << (n - 1).bit_length()
