"""Frequency-domain integration and differentiation of measured velocities (numpy only).

A laser vibrometer measures velocity; the restoring force and the loops want displacement, some
comparisons acceleration. Both conversions work on the FFT of the whole record (see each docstring).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["velocity_to_displacement", "velocity_to_acceleration"]


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


def _signal(v, fs) -> tuple[np.ndarray, float]:
    """``v`` as a non-empty 1-D float64 signal and ``fs`` as a positive frequency [Hz], else ``ValueError``."""
    x = np.asarray(v, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"v must be a non-empty 1-D signal, got shape {x.shape}")
    fs = float(fs)
    if not math.isfinite(fs) or fs <= 0:
        raise ValueError(f"fs must be a positive frequency in Hz, got {fs}")
    return x, fs


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
    x, fs = _signal(v, fs)
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
    x, fs = _signal(v, fs)
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
