"""In-memory input/output record (no file I/O here: file contents are parsed by ``storage.record_formats``,
files and folders are read by ``storage.record_files``)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
