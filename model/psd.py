"""Power spectral density (Welch) and spectral peak helpers."""
from __future__ import annotations

import numpy as np
from scipy import signal


def psd(x, fs: float, nperseg: int | None = 512, window: str = "hann", overlap: float = 0.5):
    """Welch PSD of x sampled at fs [Hz] -> (f [Hz], Pxx [units^2/Hz]).

    The paper uses both a rectangular window over the whole record (``nperseg=None,
    window='boxcar'``) and Hann segments of 2^9 samples (the default).
    """
    x = np.asarray(x, dtype=float)
    seg = x.size if nperseg is None else min(int(nperseg), x.size)
    return signal.welch(x, fs=fs, window=window, nperseg=seg, noverlap=int(seg * overlap) if seg < x.size else 0,
                        detrend="constant", scaling="density")


def peak_frequencies(x, fs: float, n_peaks: int = 3, fmin: float = 0.0, fmax: float | None = None,
                     nperseg: int | None = 512, min_separation_hz: float | None = None) -> list[float]:
    """Frequencies [Hz] of the ``n_peaks`` largest PSD peaks in [fmin, fmax], strongest first."""
    f, p = psd(x, fs, nperseg=nperseg)
    sel = (f >= fmin) & (f <= (fmax if fmax is not None else f[-1]))
    f, p = f[sel], p[sel]
    dist = None
    if min_separation_hz:
        dist = max(1, int(round(min_separation_hz / (f[1] - f[0]))))
    idx, _ = signal.find_peaks(p, distance=dist)
    if idx.size == 0:
        idx = np.array([int(np.argmax(p))])
    idx = idx[np.argsort(p[idx])[::-1]][:n_peaks]
    return [float(f[i]) for i in idx]


def band_level_db(x, fs: float, freq: float, half_width_hz: float = 0.5, nperseg: int | None = None,
                  window: str = "hann") -> float:
    """Power [dB re units^2] of x in [freq - hw, freq + hw] (e.g. a harmonic's level)."""
    f, p = psd(x, fs, nperseg=nperseg, window=window)
    sel = (f >= freq - half_width_hz) & (f <= freq + half_width_hz)
    if not sel.any():
        raise ValueError(f"no PSD bin within {half_width_hz} Hz of {freq} Hz")
    return float(10.0 * np.log10(np.sum(p[sel]) * (f[1] - f[0]) + 1e-300))
