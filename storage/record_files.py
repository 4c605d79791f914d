"""Record files and folders: readers and writers (CSV, NPZ, NPY, MATLAB .mat, LMS Test.Lab exports).

Reading
-------
``read_record(path, fs=None, name=None)`` returns a :class:`model.record.Record` and dispatches on
the path (the parsing of the file contents is :mod:`gpnarx.storage.record_formats`, shared with the
service's ``POST /v1/records/parse``):

- ``.csv``: a header line names the columns (case-insensitive, in any order): ``u`` (required),
  ``y`` (optional) and ``time`` (or ``t``) [s]. A unit may follow a column name in brackets or
  parentheses (``u [N]``, ``y (m/s)``). Several channels: one column per channel named ``u:NAME`` or
  ``y:NAME`` (``y:Acc1:+X [m/s^2]``; the name keeps its case; not mixed with a plain ``u`` / ``y``
  column of the same side). With a ``time`` column the sampling frequency is derived
  from the time step, which must be uniform (every step within 1 % of the mean step); without one,
  ``fs`` must be given. Lines starting with ``#`` and blank lines are skipped.
- ``.npz``: arrays ``u`` (required) and ``y`` (optional), scalar ``fs`` [Hz] (or the ``fs``
  argument), optional strings ``units_u``, ``units_y`` and ``name``. Loaded without pickle. Several
  channels: ``u`` (n, n_inputs) and/or ``y`` (n, n_outputs) with ``channels_u`` / ``channels_y`` (one
  name per column; a two-dimensional u or y without them is refused as before) and ``units_u`` /
  ``units_y`` one unit per channel (or one for all); at most ``MAX_CHANNELS`` (64) columns.
- ``.npy``: a 2-D array with columns ``u, y`` (``(n, 2)``) or ``u`` only (``(n,)`` or ``(n, 1)``),
  or a structured array with fields ``u``, optional ``y`` and ``time``; ``fs`` must be given unless
  there is a ``time`` field. Loaded without pickle.
- ``.mat`` (MATLAB v5, ``scipy.io.loadmat``): variables ``u``, optional ``y``, ``fs`` (or the
  argument), optional strings ``units_u``, ``units_y``. A ``Time.mat``/``TimeShaker.mat`` file of an
  LMS export is read as its folder (below).
- with the extra ``formats``: UFF-58 (``.uff``, ``.unv``), TDMS (``.tdms``), HDF5 (``.h5``,
  ``.hdf5``) and MATLAB v7.3 ``.mat`` files; how u, y and fs are found in each is in
  :mod:`gpnarx.storage.record_formats_lab`.
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
  creation time. Every channel of the export by its label: ``read_record(folder, outputs=["Laser:+X",
  "Acc1:+X", ...], inputs=["Shaker:-X"])`` (``record_formats.lms_channels``; the struct ``Signal`` of
  ``Time.mat`` holds the accelerometers ``Acc1:+X`` to ``Acc4:+X``, whose quantity label says ``g`` but
  whose values Test.Lab saved in MKS: they are read as m/s^2, untransformed; ``Time_Laser__X`` also
  names the laser). ``Record.channels`` holds each channel's name and unit.

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
``units_y``, ``name``; a record with several channels or named channels: ``u`` (n, n_inputs), ``y``
(n, n_outputs), ``channels_u``, ``channels_y`` and ``units_u``, ``units_y`` one string per channel),
``.csv`` (header ``time,u,y``, 17 significant digits; with several channels ``time,u:NAME [unit],...,y:NAME
[unit],...``) or ``.mat``
(``u``, ``y``, ``fs``, ``units_u``, ``units_y``). Writes are atomic: the data goes to a temporary
file in the destination folder which is then renamed over the destination with ``os.replace``;
on any error the temporary file is removed and an existing destination is left untouched.

The frequency-domain integration and differentiation of measured velocities (signal processing,
not file handling) is ``gpnarx.model.velocity``.
"""
from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from gpnarx.model.record import Record, RecordError
from gpnarx.storage.atomicio import atomic_file

# The parsers live in gpnarx.storage.record_formats (no filesystem access there), so the service can
# parse uploaded files without importing training; this module opens files and folders.
from gpnarx.storage.record_formats import (
    FORMATS,
    FORMATS_TEXT,
    KNOWN_UNITS,
    LMS_INPUT,
    LMS_OUTPUT,
    RecordFileError,
    check_fs,
    normalize_unit,
    parse_lms,
    parse_record,
)

__all__ = [
    "RecordFileError",
    "KNOWN_UNITS",
    "normalize_unit",
    "read_record",
    "write_record",
    "read_lms",
    "is_lms_folder",
]

_LMS_INPUT = LMS_INPUT
_LMS_OUTPUT = LMS_OUTPUT


# ============================================================================ reading
def read_record(path, fs=None, name=None, fs_default=None, inputs=None, outputs=None) -> Record:
    """Read a record file or LMS folder (see the module docstring) into a :class:`Record`.

    path: file or folder. fs: sampling frequency [Hz]; required when the file has none, checked
    against the file's otherwise. name: record name (default: the file or folder stem).
    fs_default: used only when the file carries no sampling information.
    inputs, outputs: channel names to read, in that order (None: the file's default, which for an LMS
    folder is the shaker voltage and the laser alone; ``Record.select`` for the other formats).
    """
    rec = _read_record(path, fs, name, fs_default, inputs, outputs)
    if (inputs is not None or outputs is not None) and not is_lms_folder(_lms_root(path)):
        try:
            rec = rec.select(inputs, outputs)
        except RecordError as exc:
            raise RecordFileError(path, str(exc).split(": ", 1)[-1]) from None
    return rec


def _lms_root(path) -> Path:
    p = Path(os.fspath(path)).expanduser()
    return p.parent if p.suffix.lower() == ".mat" and p.name in (_LMS_INPUT[0], _LMS_OUTPUT[0]) else p


def _read_record(path, fs, name, fs_default, inputs, outputs) -> Record:
    p = Path(os.fspath(path)).expanduser()
    if fs is not None:
        fs = check_fs(p, fs)
    if fs_default is not None and fs is None:
        fs_default = check_fs(p, fs_default)
    if not p.exists():
        raise RecordFileError(p, "no such file or folder")
    if p.is_dir():
        if is_lms_folder(p):
            return read_lms(p, fs=fs, name=name, inputs=inputs, outputs=outputs)
        raise RecordFileError(
            p, "folder is not an LMS Test.Lab export (expected Time.mat and TimeShaker.mat in it)"
        )
    ext = p.suffix.lower()
    if ext == ".mat" and p.name in (_LMS_INPUT[0], _LMS_OUTPUT[0]) and is_lms_folder(p.parent):
        return read_lms(p.parent, fs=fs, name=name, inputs=inputs, outputs=outputs)
    if ext not in FORMATS:
        raise RecordFileError(
            p, f"unsupported record format {p.suffix or '(no extension)'!r}; use {FORMATS_TEXT}"
        )
    try:
        with open(p, "rb") as fh:
            return parse_record(fh, p.name, fs=fs, name=name, fs_default=fs_default, source=p)
    except OSError as exc:
        raise RecordFileError(p, f"cannot read the file ({type(exc).__name__}: {exc})") from None


def is_lms_folder(path) -> bool:
    """True when ``path`` is a folder holding ``Time.mat`` and ``TimeShaker.mat``."""
    p = Path(path)
    return p.is_dir() and (p / _LMS_INPUT[0]).is_file() and (p / _LMS_OUTPUT[0]).is_file()


def read_lms(folder, fs=None, name=None, inputs=None, outputs=None) -> Record:
    """Read an LMS Test.Lab export folder: u = shaker voltage, y = laser velocity (see module doc); with
    ``inputs`` / ``outputs``, the channels of those names (``record_formats.parse_lms_channels``: e.g.
    ``outputs=["Laser:+X", "Acc1:+X", "Acc2:+X", "Acc3:+X", "Acc4:+X"]``, the accelerometers in m/s^2)."""
    folder = Path(folder)
    pin = folder / _LMS_INPUT[0]
    pout = folder / _LMS_OUTPUT[0]
    for f in (pin, pout):
        if not f.is_file():
            raise RecordFileError(folder, f"LMS export folder lacks {f.name}")
    try:
        with open(pin, "rb") as fin, open(pout, "rb") as fout:
            return parse_lms(fin, fout, fs=fs, name=name or folder.name, source=folder,
                             shaker_source=pin, time_source=pout, inputs=inputs, outputs=outputs)
    except OSError as exc:
        raise RecordFileError(folder, f"cannot read the LMS export ({type(exc).__name__}: {exc})") from None


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
    if ext == ".mat" and (record.u.ndim == 2 or (record.y is not None and record.y.ndim == 2)):
        raise RecordFileError(p, "a record with several channels is written as .npz (channels_u, channels_y) or "
                                 ".csv (u:NAME [unit], y:NAME [unit] columns)")
    u = np.ascontiguousarray(record.u, dtype=np.float64)
    y = None if record.y is None else np.ascontiguousarray(record.y, dtype=np.float64)
    units = {k: normalize_unit(record.units.get(k, ""), p) for k in ("u", "y")}
    try:
        with atomic_file(p) as fh:
            if ext == ".npz" and (record.channels is not None or u.ndim == 2 or (y is not None and y.ndim == 2)):
                arrays = {"u": u, "fs": np.float64(record.fs), "name": np.str_(record.name)}
                for key, chans in (("u", record.input_channels()), ("y", record.output_channels())):
                    if key == "y" and y is None:
                        continue
                    arrays[f"channels_{key}"] = np.array([c.name for c in chans], dtype=str)
                    arrays[f"units_{key}"] = np.array([normalize_unit(c.unit, p) for c in chans], dtype=str)
                if y is not None:
                    arrays["y"] = y
                np.savez(fh, **arrays)
            elif ext == ".npz":
                arrays = {"u": u, "fs": np.float64(record.fs), "units_u": np.str_(units["u"]),
                          "units_y": np.str_(units["y"]), "name": np.str_(record.name)}
                if y is not None:
                    arrays["y"] = y
                np.savez(fh, **arrays)
            elif ext == ".csv" and (record.channels is not None or u.ndim == 2 or (y is not None and y.ndim == 2)):
                buf = io.StringIO()
                head = ["time"] + [f"u:{c.name} [{c.unit}]" if c.unit else f"u:{c.name}"
                                   for c in record.input_channels()]
                cols = [np.arange(u.shape[0]) / record.fs, record.inputs_2d()]
                if y is not None:
                    head += [f"y:{c.name} [{c.unit}]" if c.unit else f"y:{c.name}" for c in record.output_channels()]
                    cols.append(record.outputs_2d())
                for c in record.input_channels() + (record.output_channels() if y is not None else []):
                    if any(ch in c.name for ch in ',;"[]()\n') or c.name != c.name.strip():
                        raise RecordFileError(p, f"channel name {c.name!r} cannot be a CSV column name; write .npz")
                buf.write(",".join(head) + "\n")
                table = np.column_stack(cols)
                for row in table:
                    buf.write(",".join("%.17g" % v for v in row) + "\n")
                fh.write(buf.getvalue().encode("utf-8"))
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
    except RecordFileError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RecordFileError(p, f"cannot write the record ({type(exc).__name__}: {exc})") from None
    return p
