"""What drives a record, and whether it is the drive a monitor was calibrated for (numpy only).

A novelty threshold is calibrated on healthy records taken with one probe excitation (the shipped
stand-in monitor: a steady 0.15 V sine at 9 Hz, free run started from measured outputs). Its score
means nothing for another drive: a healthy structure probed at 8 Hz instead of 9 Hz scores far
above the threshold because the model's band was never checked there. So a calibrated bundle
states its probe contract, and every novelty request's drive is estimated and matched against it.

Drive estimate (``drive_of``): the dominant frequency of u (Hann-windowed spectrum of the
mean-removed input, zero-padded 8x, parabolic interpolation of the log magnitude around the
peak), its ``concentration`` (share of u's variance that one least-squares sine at that frequency
explains over the whole record), and the kind: ``"sine"`` when the concentration is at least
``SINE_CONCENTRATION`` (a steady sine, even with some distortion or noise), else ``"broadband"``
(noise, multisine, and a sweep, whose phase drifts away from any single sine). Amplitude: for a
sine, the peak of that least-squares sine (robust to measurement noise, unlike the sample peak);
for a broadband drive, the RMS of u. Units: the input unit of the bundle (e.g. V or N), frequency in Hz.

Probe contract (``probe_contract``), from the healthy calibration records::

    {"kind": "sine"|"broadband", "frequency": Hz (middle of the records' dominant frequencies' range),
     "frequency_tolerance": Hz, "amplitude": [min, max] (input unit), "amplitude_kind":
     "peak"|"rms", "amplitude_tolerance": relative, "start": "measured", "n_records": int}

Matching (``probe_mismatch``): a request does not match when its start rule is not the probe's,
when its kind differs, when (sine) its
dominant frequency is off the probe's by more than ``frequency_tolerance`` =
max(``FREQ_TOL_REL`` x frequency, half the calibration records' frequency range, half a frequency
bin of the request, 0.5 / its duration [Hz], for short records), or when its amplitude lies outside the
calibrated range widened by ``AMP_TOL_REL`` (20 %) each way. The service then adds ``"probe"`` to
``out_of_range`` (see ``model.novelty.verdict`` for what the verdict is then).
"""
from __future__ import annotations

import math

import numpy as np

SINE_CONCENTRATION = 0.8  # share of the input's variance one sine explains, for a sine drive
PAD = 8  # zero-padding factor of the peak search
FREQ_TOL_REL = 0.03  # 3 %: 9 Hz +/- 0.27 Hz; an 8 Hz probe is 11 % off
AMP_TOL_REL = 0.20  # amplitude range widened 20 % each way
MIN_SAMPLES = 16
START_RULE = "measured"  # novelty scores start the free run from the record's measured outputs


def _refine_peak(mag: np.ndarray, k: int) -> float:
    """Fractional bin of a spectral peak by a parabola through the log magnitudes at k-1, k, k+1."""
    if k <= 0 or k >= mag.size - 1:
        return float(k)
    a, b, c = (math.log(max(float(v), 1e-300)) for v in mag[k - 1 : k + 2])
    den = a - 2 * b + c
    return float(k) if den == 0 else float(k + 0.5 * (a - c) / den)


def sine_fit(u, fs: float, freq: float) -> tuple[float, float, float]:
    """Least-squares ``u ~ a sin(2 pi f t) + b cos(2 pi f t) + c``: (amplitude, phase [rad], offset)
    with ``u ~ amplitude sin(2 pi f t + phase) + offset``, t = sample index / fs."""
    u = np.asarray(u, float)
    t = np.arange(u.size) / fs
    w = 2 * np.pi * freq * t
    A = np.column_stack([np.sin(w), np.cos(w), np.ones_like(w)])
    (a, b, c), *_ = np.linalg.lstsq(A, u, rcond=None)
    return float(math.hypot(a, b)), float(math.atan2(b, a)), float(c)


def drive_of(u, fs: float) -> dict:
    """Estimated drive of a record's input u sampled at fs [Hz] (see the module docstring).

    Returns ``{"kind", "frequency" [Hz], "concentration", "amplitude" [input unit],
    "amplitude_kind", "duration" [s]}``; frequency is None for a record too short or constant.
    """
    u = np.asarray(u, float)
    n = u.size
    fs = float(fs)
    out = {"kind": "broadband", "frequency": None, "concentration": 0.0,
           "amplitude": float(np.sqrt(np.mean((u - u.mean()) ** 2))) if n else 0.0, "amplitude_kind": "rms",
           "duration": n / fs}
    if n < MIN_SAMPLES or not np.all(np.isfinite(u)):
        return out
    x = (u - u.mean()) * np.hanning(n)
    if not np.any(x):
        return out
    mag = np.abs(np.fft.rfft(x, PAD * n))
    kp = int(np.argmax(mag[1:]) + 1)
    freq = _refine_peak(mag, kp) * fs / (PAD * n)
    amp, _, _ = sine_fit(u, fs, freq)
    var = float(np.var(u))
    conc = float(min(1.0, 0.5 * amp * amp / var)) if var > 0 else 0.0  # share of u's variance in the sine
    out.update(frequency=float(freq), concentration=conc)
    if conc >= SINE_CONCENTRATION:
        out.update(kind="sine", amplitude=amp, amplitude_kind="peak")
    return out


def probe_contract(records, fs: float, start: str = START_RULE) -> dict:
    """Probe contract of healthy calibration records (a list of u arrays sampled at fs [Hz])."""
    drives = [drive_of(u, fs) for u in records]
    if not drives:
        raise ValueError("at least one healthy record is needed for the probe contract")
    kinds = {d["kind"] for d in drives}
    kind = "sine" if kinds == {"sine"} else "broadband"
    if kind == "sine":
        amps = [d["amplitude"] for d in drives]
    else:  # a mixed set counts as broadband: compare RMS amplitudes
        amps = [float(np.sqrt(np.mean((np.asarray(u, float) - np.mean(u)) ** 2))) for u in records]
    freqs = [d["frequency"] for d in drives if d["frequency"] is not None]
    # the middle of the calibrated drives' range, so that the contract spans that range and no more
    freq = 0.5 * (min(freqs) + max(freqs)) if freqs else None
    tol = None
    if freq is not None:
        tol = float(max(FREQ_TOL_REL * freq, 0.5 * (max(freqs) - min(freqs))))
    return {"kind": kind, "frequency": freq, "frequency_tolerance": tol,
            "amplitude": [float(min(amps)), float(max(amps))], "amplitude_kind": "peak" if kind == "sine" else "rms",
            "amplitude_tolerance": AMP_TOL_REL, "start": start, "n_records": len(drives),
            "durations": [float(min(d["duration"] for d in drives)), float(max(d["duration"] for d in drives))]}


def check_probe(probe) -> dict | None:
    """``probe`` as a validated contract dict, or None when absent (a bundle calibrated without one)."""
    if probe is None:
        return None
    try:
        lo, hi = (float(v) for v in probe["amplitude"])
        kind = probe["kind"]
        freq = probe.get("frequency")
        freq = None if freq is None else float(freq)
    except (KeyError, TypeError, ValueError):
        raise ValueError("probe contract must hold kind, amplitude [min, max] and frequency") from None
    if kind not in ("sine", "broadband") or not (0 <= lo <= hi) or (kind == "sine" and not (freq and freq > 0)):
        raise ValueError(f"probe contract is inconsistent: kind={kind!r}, amplitude={[lo, hi]}, frequency={freq}")
    return dict(probe)


def probe_mismatch(u, fs: float, probe: dict | None, start: str | None = None) -> tuple[list[str], dict]:
    """(reasons, drive): why the drive of input u (free run started by rule ``start``, 'rest' or
    'measured') does not match ``probe`` (empty list: it matches, or the bundle states no probe) and
    the drive estimated by ``drive_of``."""
    drive = drive_of(u, fs)
    probe = check_probe(probe)
    if probe is None:
        return [], drive
    reasons = []
    if start is not None and probe.get("start") and start != probe["start"]:
        reasons.append(f"start rule {start!r} is not the probe's {probe['start']!r}")
    if drive["kind"] != probe["kind"]:
        reasons.append(f"drive is {drive['kind']}, the probe is {probe['kind']}")
    elif probe["kind"] == "sine":
        f = drive["frequency"]
        tol = max(float(probe.get("frequency_tolerance") or 0.0), FREQ_TOL_REL * float(probe["frequency"]),
                  0.5 / max(drive["duration"], 1e-12))
        if f is None or abs(f - float(probe["frequency"])) > tol:
            reasons.append(f"dominant frequency {f if f is None else round(f, 4)} Hz is not within {tol:.3g} Hz "
                           f"of the probe's {probe['frequency']:.4g} Hz")
    lo, hi = (float(v) for v in probe["amplitude"])
    tol_a = float(probe.get("amplitude_tolerance", AMP_TOL_REL))
    a = drive["amplitude"] if drive["amplitude_kind"] == probe.get("amplitude_kind", "peak") else None
    if a is None and probe.get("amplitude_kind") == "rms":
        uu = np.asarray(u, float)
        a = float(np.sqrt(np.mean((uu - uu.mean()) ** 2))) if uu.size else 0.0
    if a is not None and not (lo * (1 - tol_a) <= a <= hi * (1 + tol_a)):
        reasons.append(f"amplitude {a:.4g} is outside the probe's {lo:.4g}-{hi:.4g} widened {tol_a:.0%}")
    return reasons, drive


def probe_check(u, fs: float, probe: dict | None, start: str | None = None) -> dict:
    """``{"probe_match": True | False | None, "probe_reasons": [...], "drive": {...}}`` for a novelty
    answer: None when the bundle states no probe contract."""
    reasons, drive = probe_mismatch(u, fs, probe, start)
    return {"probe_match": None if probe is None else not reasons, "probe_reasons": reasons,
            "drive": {k: drive[k] for k in ("kind", "frequency", "amplitude", "amplitude_kind")}}


__all__ = ["AMP_TOL_REL", "FREQ_TOL_REL", "SINE_CONCENTRATION", "START_RULE", "check_probe", "drive_of",
           "probe_check", "probe_contract", "probe_mismatch", "sine_fit"]
