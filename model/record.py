"""In-memory input/output record (no file I/O here: file contents are parsed by ``storage.record_formats``,
files and folders are read by ``storage.record_files``), and the sampling-rate rule a record meets a model by
(``FS_RTOL``, ``fs_matches``; the operations' ``check_fs`` applies it to requests)."""
from __future__ import annotations

import math
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np

#: relative tolerance of a record's fs [Hz] against the model's: 10 ppm. Files that store the sample interval to
#: a few significant digits read a few ppm off (UFF-58's 6 digits: 1/750 s = 1.33333e-03 s reads 750.002 Hz, 2.7
#: ppm); within it the record is the model's rate (its fs is used), beyond it the record must be resampled
FS_RTOL = 10e-6


def fs_matches(fs: float, model_fs: float) -> bool:
    """Whether a record sampled at ``fs`` [Hz] is at the model's ``model_fs`` [Hz] within ``FS_RTOL``."""
    return math.isclose(float(fs), float(model_fs), rel_tol=FS_RTOL, abs_tol=0.0)


def resample_advice(fs: float, model_fs: float) -> str:
    """How to bring a record from ``fs`` to ``model_fs`` [Hz]: scipy's polyphase resampler with the ratio's
    integers when it is a simple fraction."""
    from fractions import Fraction

    how = f"scipy.signal.resample(x, round(len(x) * {float(model_fs):g} / {float(fs):.12g}))"
    r = float(model_fs) / float(fs)
    if math.isfinite(r) and r > 0:  # a rate next to 0 or the double range leaves no ratio of integers
        ratio = Fraction(r).limit_denominator(1000)
        if ratio > 0 and math.isclose(float(ratio), r, rel_tol=FS_RTOL):
            how = f"scipy.signal.resample_poly(x, up={ratio.numerator}, down={ratio.denominator})"
    return f"resample u and y to {float(model_fs):g} Hz first, e.g. {how}"


#: whether the records built here may hold gaps (NaN samples, ``model.gaps``): set by ``allowing_gaps``
_GAPS: ContextVar[bool] = ContextVar("gpnarx_record_gaps", default=False)


@contextmanager
def allowing_gaps():
    """Within this block, records built (``Record``, and so every record reader) may hold gaps: NaN samples in u
    or y (``model.gaps``); an infinite value is still refused. Outside it a NaN is refused, as before: only
    what takes gaps (predict, ``gpnarx validate``, ``GPNARX.fit``) reads records inside it."""
    token = _GAPS.set(True)
    try:
        yield
    finally:
        _GAPS.reset(token)


def gaps_allowed() -> bool:
    """Whether records read now may hold gaps (inside ``allowing_gaps``): what the record readers ask."""
    return _GAPS.get()


class RecordError(ValueError):
    """A record is malformed (shape, NaN/inf, length, fs)."""


#: most channels a record's u or y may hold (columns of a two-dimensional u or y)
MAX_CHANNELS = 64


@dataclass(frozen=True)
class Channel:
    """One measured signal of a record: its ``name`` (e.g. the LMS channel label ``Acc1:+X``) and ``unit``
    (e.g. ``m/s^2``; "" when not stated)."""

    name: str
    unit: str = ""

    def to_dict(self) -> dict:
        return {"name": self.name, "unit": self.unit}


@dataclass
class Record:
    """One input/output record sampled at ``fs``.

    u: input samples (e.g. force [N] or shaker voltage [V]), 1-D float64 (n,), or (n, n_inputs) for
       several input channels (one column each).
    y: output samples (e.g. displacement [m] or velocity [m/s]), 1-D float64 (n,) or (n, n_outputs), or
       None when only the excitation is known (prediction requests).
    fs: sampling frequency [Hz].
    units: ``{"u": "N", "y": "m"}`` style labels: the unit of the single input and output; with several
       channels of one unit that unit, else "" (each channel's unit is in ``channels``).
    name: free text naming where the record came from.
    meta: extra metadata (e.g. seed, amplitude, torque).
    channels: the name and unit of every channel, ``{"u": [Channel, ...], "y": [Channel, ...]}`` in column
       order; None (the default, and every single-channel reader's record) names them ``u`` and ``y``
       (``u0``, ``u1``, ... for several columns) with the units of ``units``. A (n, 1) array is one
       channel and is kept as (n,), as before.
    """

    u: np.ndarray
    y: np.ndarray | None
    fs: float
    units: dict = field(default_factory=lambda: {"u": "", "y": ""})
    name: str = "record"
    meta: dict = field(default_factory=dict)
    channels: dict | None = None

    def __post_init__(self) -> None:
        self.u = _as_signal(self.u, "u", self.name)
        if self.y is not None:
            self.y = _as_signal(self.y, "y", self.name)
            if self.y.shape[0] != self.u.shape[0]:
                raise RecordError(
                    f"{self.name}: u has {self.u.shape[0]} samples but y has {self.y.shape[0]}; they must match"
                )
        if self.channels is not None:
            self.channels = _check_channels(self.channels, self.u, self.y, self.name)
        try:
            fs = float(self.fs)
        except (TypeError, ValueError):
            raise RecordError(f"{self.name}: fs must be a number in Hz, got {self.fs!r}") from None
        if not np.isfinite(fs) or fs <= 0:
            raise RecordError(f"{self.name}: fs must be a finite positive frequency in Hz, got {fs}")
        self.fs = fs

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.u.shape[0])

    @property
    def n_inputs(self) -> int:
        """Input channels: 1 for a 1-D u, its columns otherwise."""
        return 1 if self.u.ndim == 1 else int(self.u.shape[1])

    @property
    def n_outputs(self) -> int:
        """Output channels (0 without y)."""
        if self.y is None:
            return len(self.channels["y"]) if self.channels and self.channels.get("y") else 0
        return 1 if self.y.ndim == 1 else int(self.y.shape[1])

    def input_channels(self) -> list[Channel]:
        """The name and unit of every input column (``channels``, or the defaults it documents)."""
        return self._named("u", self.n_inputs)

    def output_channels(self) -> list[Channel]:
        """The name and unit of every output column (empty without y and without named output channels)."""
        return self._named("y", self.n_outputs)

    def _named(self, key: str, k: int) -> list[Channel]:
        if self.channels is not None and self.channels.get(key) is not None:
            return list(self.channels[key])
        unit = (self.units or {}).get(key, "") or ""
        if k == 1:
            return [Channel(key, unit)]
        return [Channel(f"{key}{j}", unit) for j in range(k)]

    def inputs_2d(self) -> np.ndarray:
        """u as (n, n_inputs) (a view)."""
        return self.u[:, None] if self.u.ndim == 1 else self.u

    def outputs_2d(self) -> np.ndarray | None:
        """y as (n, n_outputs) (a view), or None."""
        if self.y is None:
            return None
        return self.y[:, None] if self.y.ndim == 1 else self.y

    def select(self, inputs=None, outputs=None) -> "Record":
        """The record with the named input and output channels only, in the order given (None: all of them);
        one channel selected gives a 1-D u or y, as a single-channel record. Its ``units`` are the selected
        channels' common unit ("" when they differ). RecordError naming the channel and those there are."""
        ins, outs = self.input_channels(), self.output_channels()
        iu = _pick(ins, inputs, "input", self.name)
        iy = _pick(outs, outputs, "output", self.name) if (outputs is not None or self.y is not None) else []
        u = self.inputs_2d()[:, iu]
        y = None if self.y is None else self.outputs_2d()[:, iy]
        cin, cout = [ins[j] for j in iu], [outs[j] for j in iy]
        units = dict(self.units)
        units["u"] = _common_unit(cin)
        if cout:
            units["y"] = _common_unit(cout)
        chans = {"u": cin, "y": cout}
        u = u[:, 0] if u.shape[1] == 1 else u
        if y is not None and y.shape[1] == 1:
            y = y[:, 0]
        return Record(np.ascontiguousarray(u), None if y is None else np.ascontiguousarray(y), self.fs, units,
                      self.name, dict(self.meta), chans)

    @property
    def t(self) -> np.ndarray:
        """Time axis [s]."""
        return np.arange(self.n) / self.fs

    def window(self, t0: float | None = None, t1: float | None = None) -> "Record":
        """Sub-record between times t0 and t1 [s] (inclusive start, exclusive end)."""
        i0 = 0 if t0 is None else int(round(t0 * self.fs))
        i1 = self.n if t1 is None else int(round(t1 * self.fs))
        if not 0 <= i0 < i1 <= self.n:
            raise RecordError(
                f"{self.name}: window [{t0}, {t1}] s is outside the record (0 to {self.n / self.fs} s)"
            )
        return Record(
            self.u[i0:i1].copy(),
            None if self.y is None else self.y[i0:i1].copy(),
            self.fs,
            dict(self.units),
            f"{self.name}[{i0}:{i1}]",
            dict(self.meta),
            None if self.channels is None else dict(self.channels),
        )


def _common_unit(chans) -> str:
    units = {c.unit for c in chans}
    return units.pop() if len(units) == 1 else ""


def _pick(chans, wanted, what: str, name: str) -> list[int]:
    if wanted is None:
        return list(range(len(chans)))
    if isinstance(wanted, str):
        wanted = [wanted]
    names = [c.name for c in chans]
    out = []
    for w in wanted:
        if w not in names:
            raise RecordError(f"{name}: no {what} channel {w!r} (channels: {', '.join(map(repr, names)) or 'none'})")
        if names.index(w) in out:
            raise RecordError(f"{name}: {what} channel {w!r} is selected twice")
        out.append(names.index(w))
    if not out:
        raise RecordError(f"{name}: select at least one {what} channel")
    return out


def _as_channel(c, key: str, name: str) -> Channel:
    if isinstance(c, Channel):
        return c
    if isinstance(c, dict):
        c = (c.get("name"), c.get("unit", ""))
    try:
        nm, unit = c
    except (TypeError, ValueError):
        raise RecordError(f"{name}: channels[{key!r}] entries must be (name, unit) pairs, got {c!r}") from None
    if not isinstance(nm, str) or not nm.strip() or not isinstance(unit, str):
        raise RecordError(f"{name}: a channel of {key} needs a non-blank name and a unit string, got {c!r}")
    return Channel(nm, unit)


def _check_channels(channels, u, y, name: str) -> dict:
    """``channels`` as {"u": [Channel], "y": [Channel]}, one per column of u and y, names unique per side."""
    if not isinstance(channels, dict) or set(channels) - {"u", "y"}:
        raise RecordError(f"{name}: channels must be a dict with keys 'u' and 'y'")
    out = {}
    for key, arr in (("u", u), ("y", y)):
        given = channels.get(key)
        if given is None:
            out[key] = None
            continue
        chans = [_as_channel(c, key, name) for c in given]
        if arr is not None:
            k = 1 if arr.ndim == 1 else arr.shape[1]
            if len(chans) != k:
                raise RecordError(f"{name}: {key} has {k} channel(s) but channels names {len(chans)}")
        names = [c.name for c in chans]
        if len(set(names)) != len(names):
            raise RecordError(f"{name}: channel names of {key} must be unique, got {names}")
        out[key] = chans
    return out


def _as_signal(a, label: str, name: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise RecordError(f"{name}: {label} must be numeric samples") from None
    if arr.ndim != 1:
        sq = np.squeeze(arr)
        if sq.ndim == 1:
            arr = sq
        elif arr.ndim == 2 and arr.shape[1] > 1 and arr.shape[0] > 1:  # (n, channels)
            if arr.shape[1] > MAX_CHANNELS:
                raise RecordError(f"{name}: {label} has {arr.shape[1]} channels (columns); at most "
                                  f"{MAX_CHANNELS} are read (a signal is (n,) or (n, channels))")
        else:
            raise RecordError(f"{name}: {label} must be 1-D (n,) or (n, channels), got shape {np.shape(a)}")
    if arr.size == 0:
        raise RecordError(f"{name}: {label} is empty")
    bad = ~np.isfinite(arr)
    if bad.any() and _GAPS.get() and not np.isinf(arr).any():
        return arr  # NaN marks gaps (``allowing_gaps``)
    if bad.any():
        raise RecordError(
            f"{name}: {label} holds {int(bad.sum())} non-finite value(s) (NaN/inf), "
            f"first at sample {int(np.argmax(bad.reshape(arr.shape[0], -1).any(axis=1)))}"
        )
    return arr
