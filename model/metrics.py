"""Prediction metrics: fit % (eq. 14), RMSE, NRMSE, band coverage and width."""
from __future__ import annotations

import numpy as np


def _pair(y, yhat):
    y = np.asarray(y, dtype=float).ravel()
    yhat = np.asarray(yhat, dtype=float).ravel()
    if y.shape != yhat.shape:
        raise ValueError(f"measured and predicted lengths differ: {y.size} vs {yhat.size}")
    if y.size == 0:
        raise ValueError("metrics need at least one sample")
    return y, yhat


def fit_percent(y, yhat) -> float:
    """Eq. (14): 100 (1 - sqrt(sum (y - mu)^2 / sum y^2)) [%]."""
    y, yhat = _pair(y, yhat)
    den = float(np.sum(y * y))
    if den == 0.0:
        return float("nan")
    return 100.0 * (1.0 - np.sqrt(float(np.sum((y - yhat) ** 2)) / den))


def rmse(y, yhat) -> float:
    """Root-mean-square error, in output units."""
    y, yhat = _pair(y, yhat)
    return float(np.sqrt(np.mean((y - yhat) ** 2)))


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
    """All metrics for a measured record y against a prediction."""
    out = {"fit": fit_percent(y, mean), "rmse": rmse(y, mean), "nrmse": nrmse(y, mean)}
    if lower is not None and upper is not None:
        out["coverage"] = coverage(y, lower, upper)
        out["band_width"] = band_width(lower, upper)
    return out
