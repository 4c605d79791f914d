"""Prediction metrics: fit % (eq. 14), RMSE, NRMSE, band coverage and width."""
from __future__ import annotations

import math

import numpy as np


def _pair(y, yhat):
    y = np.asarray(y, dtype=float).ravel()
    yhat = np.asarray(yhat, dtype=float).ravel()
    if y.shape != yhat.shape:
        raise ValueError(f"measured and predicted lengths differ: {y.size} vs {yhat.size}")
    if y.size == 0:
        raise ValueError("metrics need at least one sample")
    return y, yhat


def rms(a) -> float:
    """Root mean square of the samples of ``a`` (same unit), sqrt(mean(a^2)) taken on a / max|a|: finite for any
    finite samples (the squares of samples beyond 1.3e154 overflow a double); inf when a sample is not finite, nan
    for no samples."""
    a = np.asarray(a, dtype=float).ravel()
    if a.size == 0:
        return float("nan")
    peak = float(np.max(np.abs(a)))
    if peak == 0.0 or not math.isfinite(peak):
        return peak if not math.isnan(peak) else float("nan")
    b = a / peak
    return peak * math.sqrt(float(np.mean(b * b)))


def fit_percent(y, yhat) -> float:
    """Eq. (14): 100 (1 - sqrt(sum (y - mu)^2 / sum y^2)) [%] (as a ratio of RMS values: ``rms``)."""
    y, yhat = _pair(y, yhat)
    den = rms(y)
    if den == 0.0:
        return float("nan")
    return 100.0 * (1.0 - rms(y - yhat) / den)


def rmse(y, yhat) -> float:
    """Root-mean-square error, in output units (``rms``: no overflow for large finite errors)."""
    y, yhat = _pair(y, yhat)
    return rms(y - yhat)


def nrmse(y, yhat) -> float:
    """RMSE normalised by the standard deviation of the measured output (dimensionless)."""
    y, yhat = _pair(y, yhat)
    sd = float(np.std(y))
    return float("nan") if sd == 0 else rmse(y, yhat) / sd


def coverage(y, lower, upper) -> float:
    """Percent of measured samples inside [lower, upper]."""
    y, lower = _pair(y, lower)
    _, upper = _pair(y, upper)
    return 100.0 * float(np.mean((y >= lower) & (y <= upper)))


def band_width(lower, upper) -> float:
    """Mean width of the band, in output units."""
    return float(np.mean(np.asarray(upper, float) - np.asarray(lower, float)))


def summary(y, mean, lower=None, upper=None) -> dict:
    """All metrics for a measured record y against a prediction. Gaps (``model.gaps``: NaN in y or in the
    prediction) are skipped: the metrics are those of the samples measured and predicted."""
    y, mean = _pair(y, mean)
    gap = np.isnan(y) | np.isnan(mean)
    if gap.any():
        keep = ~gap
        if lower is not None and upper is not None:
            lower, upper = np.asarray(lower, float).ravel()[keep], np.asarray(upper, float).ravel()[keep]
        y, mean = y[keep], mean[keep]
    out = {"fit": fit_percent(y, mean), "rmse": rmse(y, mean), "nrmse": nrmse(y, mean)}
    if lower is not None and upper is not None:
        out["coverage"] = coverage(y, lower, upper)
        out["band_width"] = band_width(lower, upper)
    return out
