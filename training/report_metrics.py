"""Scalar metrics of one record of a validation report: fit (eq. 14), RMSE, both coverages, band width,
PSD peaks, loop areas and harmonic levels, JSON-ready; and the record's part in the study (its use)."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from gpnarx.model import metrics as _metrics
from gpnarx.model import psd as _psd
from gpnarx.model.restoring import loop_area, restoring_force

PSD_NPERSEG = 512  # 2^9 Hann segments (paper, sine records)
N_HARMONICS = 3
N_PEAKS = 3
_MAX_JSON_ARRAY = 64  # arrays longer than this are not written to report.json


def _arr(x):
    return None if x is None else np.asarray(x, dtype=float).ravel()


def unpack_record(rec: dict) -> dict:
    """Arrays of a record as float vectors, with time axis and units filled in."""
    fs = float(rec["fs"])
    if not fs > 0:
        raise ValueError(f"record {rec.get('name')!r}: fs must be positive, got {fs}")
    mean = _arr(rec.get("mean"))
    if mean is None:
        raise ValueError(f"record {rec.get('name')!r} has no model mean")
    n = mean.size
    d = {"fs": fs, "n": n, "mean": mean}
    for k in ("u", "y", "y_clean", "lower", "upper", "latent_lower", "latent_upper"):
        v = _arr(rec.get(k))
        if v is not None and v.size != n:
            raise ValueError(f"record {rec.get('name')!r}: {k} has {v.size} samples, mean has {n}")
        d[k] = v
    t = _arr(rec.get("t"))
    if t is None or t.size != n:
        t = np.arange(n) / fs
    d["t"] = t
    units = rec.get("units") or {}
    d["uu"] = units.get("u", "")
    d["uy"] = units.get("y", "")
    return d


def psd_options(rec: dict, n: int) -> tuple[int | None, str]:
    opts = rec.get("psd") or {}
    nperseg = opts.get("nperseg", PSD_NPERSEG)
    if nperseg is not None and nperseg >= n:
        nperseg = None  # whole record when shorter than one segment
    return nperseg, opts.get("window", "hann")


def loop_of(u, y, fs, physics):
    """(x, R) for the hysteresis panel / loop area; None when physics has no mass."""
    if not physics or not physics.get("mass"):
        return None
    return restoring_force(u, y, fs, float(physics["mass"]), input_gain=float(physics.get("input_gain", 1.0)),
                           output=physics.get("output", "displacement"))


def finite_or_none(v):
    """float or None (NaN / inf -> None)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def to_report_json(o):
    """Recursively convert numpy / Path / tuples to JSON types; NaN and inf become None."""
    if isinstance(o, dict):
        return {str(k): to_report_json(v) for k, v in o.items()}
    if isinstance(o, np.ndarray):
        if o.size > _MAX_JSON_ARRAY:
            return {"omitted_array_shape": list(o.shape)}
        return [to_report_json(v) for v in o.tolist()]
    if isinstance(o, (list, tuple)):
        return [to_report_json(v) for v in o]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return finite_or_none(o)
    if isinstance(o, Path):
        return str(o)
    if o is None or isinstance(o, str):
        return o
    return str(o)


def slug(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    return s or "record"


def _harmonic_levels(x, fs, f0, n) -> list:
    out = []
    band = getattr(_psd, "band_level_db", None)
    hw = max(0.5, 2.0 * fs / n)
    for k in range(1, N_HARMONICS + 1):
        fk = k * f0
        if fk + hw > fs / 2:
            out.append(None)
            continue
        try:
            if band is not None:
                out.append(finite_or_none(band(x, fs, fk, half_width_hz=hw)))
            else:
                f, p = _psd.psd(x, fs, nperseg=None)
                sel = (f >= fk - hw) & (f <= fk + hw)
                level = 10 * np.log10(np.sum(p[sel]) * (f[1] - f[0]) + 1e-300) if sel.any() else None
                out.append(finite_or_none(level))
        except ValueError:
            out.append(None)
    return out


USES = {"training": "a training record (its rows trained the model)",
        "lag-selection": "a lag-selection record (the lag surface was judged on it)",
        "calibration": "a novelty-calibration record (healthy; the threshold was set on it)",
        "held-out": "a held-out record (used for no fit and no choice)"}


def record_use(roles) -> str | None:
    """A record's part in the study from its config roles: 'training' (role train, whatever else it
    is scored as, e.g. a verify record that is also trained on), 'lag-selection' (lags), 'calibration'
    (healthy: the novelty threshold's records), else 'held-out' (verify, validate, damaged)."""
    if not roles:
        return None
    roles = {str(r) for r in roles}
    if "train" in roles:
        return "training"
    if "lags" in roles:
        return "lag-selection"
    if "healthy" in roles:
        return "calibration"
    return "held-out"


def record_metrics(rec: dict, physics: dict | None = None) -> dict:
    """Scalar metrics of one record (JSON-ready: NaN -> None, no big arrays).

    fit, rmse, nrmse, coverage (the predictive band, noise sigma_y^2 included), band_width against the
    measured ``y`` (when present); fit_clean, rmse_clean against ``y_clean`` and coverage_latent, the
    latent band (``latent_lower``/``latent_upper``, no noise term) against ``y_clean`` (a band holding
    the noise scored against the noise-free output would over-cover); ``use``, the record's part in the
    study from its config ``roles`` (:func:`record_use`); the 3 strongest PSD peaks [Hz] of
    measured and predicted output; loop areas [J] when ``physics`` has a mass (measured, predicted and,
    with ``y_clean``, noise-free ``loop_area_clean``); for sine records
    (``drive_freq``) the levels [dB] of harmonics 1..3 of measured and predicted output.
    """
    d = unpack_record(rec)
    fs, n, mean, lo, up = d["fs"], d["n"], d["mean"], d["lower"], d["upper"]
    has_band = lo is not None and up is not None
    out: dict = {"n_samples": n, "duration_s": n / fs}
    if d["y"] is not None:
        out.update(_metrics.summary(d["y"], mean, lo, up) if has_band else _metrics.summary(d["y"], mean))
    elif has_band:
        out["band_width"] = _metrics.band_width(lo, up)
    if d["y_clean"] is not None:
        out["fit_clean"] = _metrics.fit_percent(d["y_clean"], mean)
        out["rmse_clean"] = _metrics.rmse(d["y_clean"], mean)
        if d["latent_lower"] is not None and d["latent_upper"] is not None:
            out["coverage_latent"] = _metrics.coverage(d["y_clean"], d["latent_lower"], d["latent_upper"])
    use = record_use(rec.get("roles"))
    if use:
        out["use"] = use

    nperseg, window = psd_options(rec, n)
    fmin, fmax = rec.get("freq_range") or (0.0, None)
    if n >= 8:
        if d["y"] is not None:
            out["psd_peaks_measured"] = _psd.peak_frequencies(d["y"], fs, n_peaks=N_PEAKS, fmin=fmin, fmax=fmax,
                                                              nperseg=nperseg)
        out["psd_peaks_predicted"] = _psd.peak_frequencies(mean, fs, n_peaks=N_PEAKS, fmin=fmin, fmax=fmax,
                                                           nperseg=nperseg)

    if physics and physics.get("mass") and d["u"] is not None:
        out["loop_area_predicted"] = loop_area(*loop_of(d["u"], mean, fs, physics))
        if d["y"] is not None:
            out["loop_area_measured"] = loop_area(*loop_of(d["u"], d["y"], fs, physics))
        if d["y_clean"] is not None:
            out["loop_area_clean"] = loop_area(*loop_of(d["u"], d["y_clean"], fs, physics))

    f0 = rec.get("drive_freq")
    if f0:
        f0 = float(f0)
        out["drive_freq"] = f0
        if d["y"] is not None:
            out["harmonics_db_measured"] = _harmonic_levels(d["y"], fs, f0, n)
        out["harmonics_db_predicted"] = _harmonic_levels(mean, fs, f0, n)
    return to_report_json(out)
