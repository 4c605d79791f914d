"""In-memory input/output record (no file I/O here: file contents are parsed by ``storage.record_formats``,
files and folders are read by ``storage.record_files``), and the sampling-rate rule a record meets a model by
(``FS_RTOL``, ``fs_matches``; the operations' ``check_fs`` applies it to requests)."""
from __future__ import annotations

import math
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


class RecordError(ValueError):
    """A record is malformed (shape, NaN/inf, length, fs)."""


@dataclass
class Record:
    """One input/output record sampled at ``fs``.

    u: input samples (e.g. force [N] or shaker voltage [V]), 1-D float64.
    y: output samples (e.g. displacement [m] or velocity [m/s]), 1-D float64, or None when only
       the excitation is known (prediction requests).
    fs: sampling frequency [Hz].
    units: ``{"u": "N", "y": "m"}`` style labels.
    name: free text naming where the record came from.
    meta: extra metadata (e.g. seed, amplitude, torque).
    """

    u: np.ndarray
    y: np.ndarray | None
    fs: float
    units: dict = field(default_factory=lambda: {"u": "", "y": ""})
    name: str = "record"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.u = _as_signal(self.u, "u", self.name)
        if self.y is not None:
            self.y = _as_signal(self.y, "y", self.name)
            if self.y.shape != self.u.shape:
                raise RecordError(
                    f"{self.name}: u has {self.u.size} samples but y has {self.y.size}; they must match"
                )
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
        return int(self.u.size)

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
        )


def _as_signal(a, label: str, name: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise RecordError(f"{name}: {label} must be numeric samples") from None
    if arr.ndim != 1:
        arr = np.squeeze(arr)
        if arr.ndim != 1:
            raise RecordError(f"{name}: {label} must be 1-D, got shape {np.shape(a)}")
    if arr.size == 0:
        raise RecordError(f"{name}: {label} is empty")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise RecordError(
            f"{name}: {label} holds {int(bad.sum())} non-finite value(s) (NaN/inf), "
            f"first at sample {int(np.argmax(bad))}"
        )
    return arr
