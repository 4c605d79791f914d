"""Excitation signals for the simulators and the protocols of sections 3 and 4.

Every generator returns a 1-D ``float64`` array sampled at ``fs`` [Hz], sample ``n`` at time
``t = n / fs`` [s] (see :func:`time_axis`). Amplitudes are in the input's units: force [N] for the
Bouc-Wen benchmark, shaker voltage [V] for the BERT stand-in. Frequencies are in Hz, rates in Hz/s,
durations in s. Invalid arguments raise ``ValueError`` naming the offending argument.

Conventions
-----------
- The number of samples for a ``duration`` is ``round(duration * fs)``.
- ``swept_sine`` and ``sine`` use ``amplitude`` as the *peak* value.
- ``multisine`` and ``band_limited_noise`` use their amplitude as the *RMS* value, like the
  benchmark's multisine level ``A`` (Noel & Schoukens 2016: random-phase multisine, 5-150 Hz,
  8192 samples per period at 750 Hz, level given as an RMS force).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "time_axis",
    "n_samples",
    "swept_sine",
    "sweep_duration",
    "sine",
    "multisine",
    "multisine_lines",
    "band_limited_noise",
]


# ----------------------------------------------------------------------------- validation helpers
def _finite(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def _positive(name: str, value) -> float:
    v = _finite(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {v:g}")
    return v


def _nonnegative(name: str, value) -> float:
    v = _finite(name, value)
    if v < 0:
        raise ValueError(f"{name} must be >= 0, got {v:g}")
    return v


def _band(fs: float, f0, f1, *, allow_zero_f0: bool = True) -> tuple[float, float]:
    f0 = _nonnegative("f0", f0) if allow_zero_f0 else _positive("f0", f0)
    f1 = _positive("f1", f1)
    if f1 <= f0:
        raise ValueError(f"f1 must be greater than f0, got f0={f0:g} Hz, f1={f1:g} Hz")
    if fs <= 2.0 * f1:
        raise ValueError(
            f"fs must exceed twice f1 (Nyquist): fs={fs:g} Hz but f1={f1:g} Hz needs fs > {2 * f1:g} Hz"
        )
    return f0, f1


def n_samples(fs: float, duration: float) -> int:
    """Number of samples ``round(duration * fs)`` of a record lasting ``duration`` [s] at ``fs`` [Hz]."""
    fs = _positive("fs", fs)
    duration = _positive("duration", duration)
    n = int(round(duration * fs))
    if n < 1:
        raise ValueError(f"duration {duration:g} s is shorter than one sample at fs={fs:g} Hz")
    return n


def time_axis(fs: float, n: int) -> np.ndarray:
    """Time axis ``t[k] = k / fs`` [s] of ``n`` samples at ``fs`` [Hz]."""
    fs = _positive("fs", fs)
    if int(n) != n or n < 0:
        raise ValueError(f"n must be a non-negative integer, got {n!r}")
    return np.arange(int(n), dtype=np.float64) / fs


# ----------------------------------------------------------------------------- sweeps and sines
def sweep_duration(f0: float, f1: float, rate: float | None = None, duration: float | None = None) -> float:
    """Duration [s] of a linear sweep from ``f0`` to ``f1`` [Hz] given exactly one of ``rate`` [Hz/s]
    or ``duration`` [s] (or both, when consistent)."""
    if rate is None and duration is None:
        raise ValueError("rate or duration: give one of them (sweep rate in Hz/s, or duration in s)")
    if rate is not None:
        rate = _positive("rate", rate)
        d = (f1 - f0) / rate
        if duration is not None:
            duration = _positive("duration", duration)
            if not math.isclose(duration, d, rel_tol=1e-9, abs_tol=1e-12):
                raise ValueError(
                    f"duration {duration:g} s is inconsistent with rate {rate:g} Hz/s "
                    f"(a {f0:g}-{f1:g} Hz sweep at that rate lasts {d:g} s); give only one"
                )
        return d
    return _positive("duration", duration)


def swept_sine(
    fs: float,
    amplitude: float,
    f0: float,
    f1: float,
    rate: float | None = None,
    duration: float | None = None,
    phase: float = 0.0,
) -> np.ndarray:
    """Linear swept sine ``amplitude * sin(2 pi (f0 t + rate t^2 / 2) + phase)``.

    fs: sampling frequency [Hz], must exceed ``2 * f1``.
    amplitude: peak value in input units (N or V), >= 0.
    f0, f1: start and end frequency [Hz], ``0 <= f0 < f1``.
    rate: sweep rate [Hz/s]; instantaneous frequency is ``f0 + rate * t``.
    duration: sweep duration [s]; if ``rate`` is not given, ``rate = (f1 - f0) / duration``.
        Give one of ``rate``/``duration`` (both only if consistent).
    phase: initial phase [rad].

    Returns ``round(duration * fs)`` samples at ``t = k / fs``.
    """
    fs = _positive("fs", fs)
    amplitude = _nonnegative("amplitude", amplitude)
    f0, f1 = _band(fs, f0, f1)
    phase = _finite("phase", phase)
    d = sweep_duration(f0, f1, rate, duration)
    r = (f1 - f0) / d
    t = time_axis(fs, n_samples(fs, d))
    return amplitude * np.sin(2.0 * np.pi * (f0 * t + 0.5 * r * t * t) + phase)


def sine(fs: float, amplitude: float, freq: float, duration: float, phase: float = 0.0) -> np.ndarray:
    """Stationary sine ``amplitude * sin(2 pi freq t + phase)``.

    fs [Hz] (> 2 freq), amplitude: peak in input units (N or V), freq [Hz] > 0, duration [s],
    phase [rad].
    """
    fs = _positive("fs", fs)
    amplitude = _nonnegative("amplitude", amplitude)
    freq = _positive("freq", freq)
    if fs <= 2.0 * freq:
        raise ValueError(f"fs must exceed twice freq (Nyquist): fs={fs:g} Hz, freq={freq:g} Hz")
    phase = _finite("phase", phase)
    t = time_axis(fs, n_samples(fs, duration))
    return amplitude * np.sin(2.0 * np.pi * freq * t + phase)


# ----------------------------------------------------------------------------- multisine
def _n_per_period(n) -> int:
    if isinstance(n, bool) or int(n) != n or n < 2:
        raise ValueError(f"n_per_period must be an integer >= 2, got {n!r}")
    return int(n)


def _line_indices(fs: float, f0: float, f1: float, n: int) -> np.ndarray:
    df = fs / n
    k_lo = max(1, math.ceil(f0 / df - 1e-9))
    k_hi = min((n - 1) // 2, math.floor(f1 / df + 1e-9))  # never the DC or the Nyquist line
    return np.arange(k_lo, k_hi + 1, dtype=np.int64)


def multisine_lines(fs: float, f0: float, f1: float, n: int, return_index: bool = False):
    """Frequencies [Hz] of the DFT lines excited by :func:`multisine`.

    The period has ``n`` samples at ``fs`` [Hz], so lines are spaced ``fs / n`` Hz; every line
    ``k * fs / n`` with ``f0 <= k fs / n <= f1`` and ``k >= 1`` is excited (DC never is).
    With ``return_index=True`` returns ``(freqs, k)``.
    """
    fs = _positive("fs", fs)
    f0, f1 = _band(fs, f0, f1)
    n = _n_per_period(n)
    k = _line_indices(fs, f0, f1, n)
    if k.size == 0:
        raise ValueError(
            f"f0/f1: no DFT line of a {n}-sample period (spacing {fs / n:g} Hz) lies in [{f0:g}, {f1:g}] Hz"
        )
    freqs = k * (fs / n)
    return (freqs, k) if return_index else freqs


def multisine(
    fs: float,
    amplitude: float | None,
    f0: float,
    f1: float,
    n_per_period: int,
    n_periods: int = 1,
    seed=None,
    rms: float | None = None,
) -> np.ndarray:
    """Random-phase multisine as in the Noel & Schoukens (2016) Bouc-Wen benchmark.

    One period has ``n_per_period`` samples at ``fs`` [Hz]. All DFT lines in ``[f0, f1]`` (see
    :func:`multisine_lines`) get the same amplitude and independent phases uniform in
    ``[0, 2 pi)`` drawn from ``numpy.random.default_rng(seed)``; every other line is zero. The
    period is scaled so that its RMS value equals ``amplitude`` (input units, e.g. N RMS, like the
    benchmark's level ``A``); the peak is typically 3-4 times the RMS. ``rms`` is a synonym of
    ``amplitude`` for callers that want to be explicit: give one of them (both only if equal).

    Returns ``n_periods`` identical periods concatenated (``n_periods * n_per_period`` samples).
    """
    if amplitude is None and rms is None:
        raise ValueError("amplitude: give the multisine RMS level (amplitude or rms)")
    if amplitude is not None and rms is not None and float(amplitude) != float(rms):
        raise ValueError(f"rms: {rms!r} conflicts with amplitude {amplitude!r}; both are the RMS, give one")
    level = _nonnegative("amplitude" if amplitude is not None else "rms", amplitude if amplitude is not None else rms)
    if isinstance(n_periods, bool) or int(n_periods) != n_periods or n_periods < 1:
        raise ValueError(f"n_periods must be an integer >= 1, got {n_periods!r}")
    n = _n_per_period(n_per_period)
    _, k = multisine_lines(fs, f0, f1, n, return_index=True)
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=k.size)
    spec = np.zeros(n // 2 + 1, dtype=np.complex128)
    spec[k] = np.exp(1j * phases)
    x = np.fft.irfft(spec, n)
    x *= level / np.sqrt(np.mean(x * x))
    return np.tile(x, int(n_periods)).astype(np.float64, copy=False)


# ----------------------------------------------------------------------------- band-limited noise
def band_limited_noise(fs: float, duration: float, f0: float, f1: float, rms: float, seed=None) -> np.ndarray:
    """Gaussian white noise band-limited to ``[f0, f1]`` [Hz] in the frequency domain.

    ``round(duration * fs)`` samples of white Gaussian noise from ``numpy.random.default_rng(seed)``
    are transformed with an FFT, every bin outside ``[f0, f1]`` (and the DC bin) is zeroed, and the
    inverse FFT is scaled so the sample RMS equals ``rms`` exactly (input units, N or V RMS).
    ``f0`` may be 0 (band from the first non-DC bin). fs [Hz] must exceed ``2 * f1``.
    """
    fs = _positive("fs", fs)
    f0, f1 = _band(fs, f0, f1)
    rms = _nonnegative("rms", rms)
    n = n_samples(fs, duration)
    freqs = np.fft.rfftfreq(n, 1.0 / fs)
    keep = (freqs >= f0) & (freqs <= f1) & (freqs > 0)
    if not keep.any():
        raise ValueError(
            f"duration: {duration:g} s gives a bin spacing of {fs / n:g} Hz with no bin in [{f0:g}, {f1:g}] Hz"
        )
    rng = np.random.default_rng(seed)
    spec = np.fft.rfft(rng.standard_normal(n))
    spec[~keep] = 0.0
    x = np.fft.irfft(spec, n)
    cur = np.sqrt(np.mean(x * x))
    if cur > 0:
        x *= rms / cur
    return x.astype(np.float64, copy=False)
