"""Residual tests of a fitted model: whiteness of its one-step residuals and their independence of the input.

The standard model check of system identification (Ljung, *System Identification*, 2nd ed., section 16.6;
MATLAB ``resid``, SysIdentPy's residual plots): a model that has learnt the dynamics leaves one-step-ahead
residuals e(t) = y(t) - yhat(t | t-1) that are white and uncorrelated with past inputs, however good its fit.

* **Residuals.** The one-step-ahead prediction of eqs. 8-9 from measured lags (``GPNARX.predict_one_step``), in
  output units: e = y - mean. The correlation tests use these raw residuals, as MATLAB ``resid`` does; a
  normalised correlation does not depend on e's scale, and dividing each sample by its own one-step std
  would weight the samples unequally, which the limits below do not assume. The one-step std is used for
  the one-step band's coverage and the RMS of the standardised residuals z = e / std (about 1 when the
  one-step band is calibrated) only (``one_step_check(..., with_std=True)``).
* **Autocorrelation** of e, mean removed, at lags 1..L (default 25, as MATLAB ``resid``):
  r_e(k) = c_e(k) / c_e(0), c_e(k) = (1/N) sum_t e(t) e(t-k).
* **Cross-correlation** of u and e, both means removed, at lags -L..L: r_ue(k) = c_ue(k) / sqrt(c_u(0) c_e(0)),
  c_ue(k) = (1/N) sum_t u(t) e(t+k). A positive lag k is the input k samples before the residual (what an
  unlearnt dynamic leaves); a negative lag, the residual before the input (feedback).
* **Confidence limits** +-z / sqrt(N) (z = 2.576 at 99 %). They hold under the null hypothesis that e is white
  (independent, zero-mean, of constant variance) and, for the cross-correlation, independent of u: each
  normalised correlation is then asymptotically normal with variance 1/N. The cross-correlation's limit is
  exact for a white e whatever u's own colour (Var c_ue(k) = (1/N) sum_j R_u(j) R_e(j) = R_u(0) R_e(0) / N);
  with a coloured e it is too narrow, which is the failure the autocorrelation test already reports.
* **Share of lags outside** the limits: about 1 - confidence (1 %) for a white residual.
* **Ljung-Box** Q = N (N + 2) sum_{k=1..L} r_e(k)^2 / (N - k), chi-square with L degrees of freedom under
  whiteness (no degrees subtracted for the model's parameters: a GP has no fixed count, and MATLAB and
  SysIdentPy subtract none). For the cross-correlation, the portmanteau S = N sum_{k=-L..L} r_ue(k)^2,
  chi-square with 2L + 1 degrees of freedom (Box and Jenkins' cross-correlation check).
  The verdicts ``white`` and ``independent`` are p >= 1 - confidence.

The correlations are computed by FFT (zero-padded past N + L, so none wraps around): O(N log N) for a whole
64 s record at 1024 Hz. ``scipy.stats`` (the chi-square tail) is imported inside the functions that need it,
so importing this module costs a command's start-up nothing.
"""
from __future__ import annotations

import math

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.metrics import fit_percent, rms, rmse
from gpnarx.model.normal import band_z
from gpnarx.model.regressors import first_index

#: lags of the tests (MATLAB ``resid``'s default)
DEFAULT_LAGS = 25
#: confidence of the limits and of the verdicts
DEFAULT_CONFIDENCE = 0.99
#: one-step predictions per call of the posterior (a (rows x training rows) kernel block at a time)
ONE_STEP_BLOCK = 4096

__all__ = ["DEFAULT_CONFIDENCE", "DEFAULT_LAGS", "autocorrelation", "chi2_sf", "cross_correlation",
           "ljung_box", "one_step_check", "one_step_prediction", "residual_tests"]


def _series(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D series, got an array of shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite samples: the residual tests need a gap-free record")
    return a


def _check_lags(lags, n: int) -> int:
    if not is_int(lags, 1):
        raise ValueError(f"lags must be a positive integer, got {lags!r}")
    if n <= 2 * int(lags):
        raise ValueError(f"the residual tests at {lags} lags need more than {2 * int(lags)} residuals, got {n}")
    return int(lags)


def _nfft(n: int) -> int:
    """A power of two >= n (numpy's FFT is fastest there)."""
    return 1 << max(0, int(n - 1).bit_length())


def _centred(a: np.ndarray) -> tuple[np.ndarray, float]:
    """``a`` with its mean removed and c(0) = mean of its squares (0 for a constant series)."""
    d = a - a.mean()
    return d, float(np.dot(d, d)) / a.size


def autocorrelation(e, lags: int = DEFAULT_LAGS) -> np.ndarray:
    """r_e(1..lags): the normalised autocorrelation of ``e`` (mean removed, biased estimator c(k) / c(0)).

    NaN for a constant ``e`` (no variance to normalise by)."""
    e = _series("e", e)
    lags = _check_lags(lags, e.size)
    d, c0 = _centred(e)
    if c0 == 0.0:
        return np.full(lags, np.nan)
    spec = np.fft.rfft(d, _nfft(d.size + lags))
    c = np.fft.irfft(spec.real ** 2 + spec.imag ** 2, _nfft(d.size + lags))[1:lags + 1] / d.size
    return c / c0


def cross_correlation(u, e, lags: int = DEFAULT_LAGS) -> np.ndarray:
    """r_ue(-lags..lags): the normalised cross-correlation (1/N) sum_t u(t) e(t+k) / sqrt(c_u(0) c_e(0)),
    both means removed; index ``lags + k`` holds lag k. NaN for a constant ``u`` or ``e``."""
    u, e = _series("u", u), _series("e", e)
    if u.size != e.size:
        raise ValueError(f"u and e must have the same length, got {u.size} and {e.size}")
    lags = _check_lags(lags, e.size)
    du, cu = _centred(u)
    de, ce = _centred(e)
    if cu == 0.0 or ce == 0.0:
        return np.full(2 * lags + 1, np.nan)
    m = _nfft(e.size + lags)
    c = np.fft.irfft(np.conj(np.fft.rfft(du, m)) * np.fft.rfft(de, m), m) / e.size
    # c[k] = (1/N) sum_t du(t) de(t+k) for k >= 0, c[m - k] the lag -k
    return np.concatenate([c[m - lags:], c[:lags + 1]]) / math.sqrt(cu * ce)


def chi2_sf(q: float, df: int) -> float:
    """P(X >= q) for X chi-square with ``df`` degrees of freedom (scipy.stats, imported here)."""
    from scipy.stats import chi2

    return float(chi2.sf(q, df))


def ljung_box(r, n: int) -> dict:
    """Ljung-Box Q = n (n + 2) sum_k r(k)^2 / (n - k) over the autocorrelations ``r`` at lags 1..len(r) of
    ``n`` residuals, its degrees of freedom (len(r)) and p-value (the chi-square tail)."""
    r = np.asarray(r, dtype=np.float64)
    k = np.arange(1, r.size + 1)
    q = float(n * (n + 2) * np.sum(r * r / (n - k)))
    return {"q": q, "df": int(r.size), "p_value": chi2_sf(q, r.size) if np.isfinite(q) else float("nan")}


def _outside(r: np.ndarray, limit: float) -> tuple[int, float]:
    finite = np.isfinite(r)
    k = int(np.count_nonzero(np.abs(r[finite]) > limit))
    return k, (k / int(finite.sum()) if finite.any() else float("nan"))


def residual_tests(e, u=None, lags: int = DEFAULT_LAGS, confidence: float = DEFAULT_CONFIDENCE) -> dict:
    """Whiteness of the residuals ``e`` and their cross-correlation with the input ``u`` (aligned with e;
    None: the autocorrelation only), at lags 1..``lags`` (-lags..lags for the cross-correlation), with the
    ``confidence`` limits +-z / sqrt(N) (the module docstring: what they assume).

    Returns a JSON-ready dict: ``n``, ``lags``, ``confidence``, ``limit``; ``autocorrelation`` {``lag``, ``r``,
    ``n_outside``, ``outside_share``, ``ljung_box`` {``q``, ``df``, ``p_value``}, ``white``};
    ``cross_correlation`` {``lag``, ``r``, ``n_outside``, ``outside_share``, ``portmanteau`` {``q``, ``df``,
    ``p_value``}, ``independent``} (None without ``u``); ``passed`` (white and independent). A verdict is
    None where a series is constant (no correlation to normalise)."""
    e = _series("e", e)
    lags = _check_lags(lags, e.size)
    n = e.size
    alpha = 1.0 - float(confidence)
    limit = band_z(confidence) / math.sqrt(n)
    r = autocorrelation(e, lags)
    k_out, share = _outside(r, limit)
    lb = ljung_box(r, n)
    white = None if not np.isfinite(lb["p_value"]) else bool(lb["p_value"] >= alpha)
    out = {"n": n, "lags": lags, "confidence": float(confidence), "limit": limit,
           "autocorrelation": {"lag": list(range(1, lags + 1)), "r": r.tolist(), "n_outside": k_out,
                               "outside_share": share, "ljung_box": lb, "white": white},
           "cross_correlation": None}
    independent = True
    if u is not None:
        x = cross_correlation(u, e, lags)
        kx, sx = _outside(x, limit)
        q = float(n * np.sum(x * x))
        port = {"q": q, "df": int(x.size), "p_value": chi2_sf(q, x.size) if np.isfinite(q) else float("nan")}
        independent = None if not np.isfinite(q) else bool(port["p_value"] >= alpha)
        out["cross_correlation"] = {"lag": list(range(-lags, lags + 1)), "r": x.tolist(), "n_outside": kx,
                                    "outside_share": sx, "portmanteau": port, "independent": independent}
    out["passed"] = None if white is None or independent is None else bool(white and independent)
    return out


def one_step_prediction(model, u, y, with_std: bool = False, block: int = ONE_STEP_BLOCK):
    """The one-step-ahead mean (and std with ``with_std``) of a fitted ``GPNARX`` on the record (u, y), eqs. 8-9
    from measured lags (``model.predict_one_step``), ``block`` samples per call; aligned with the samples
    i0 = max(ny, nu - 1) onwards. Returns (i0, mean, std or None)."""
    u, y = _series("u", u), _series("y", y)
    if u.size != y.size:
        raise ValueError(f"u and y must have the same length, got {u.size} and {y.size} samples")
    i0 = first_index(model.ny, model.nu)
    if y.size <= i0:
        raise ValueError(f"record has {y.size} samples; one-step prediction needs more than {i0}")
    mean = np.empty(y.size - i0)
    std = np.empty(y.size - i0) if with_std else None
    for s in range(i0, y.size, int(block)):
        t = min(y.size, s + int(block))
        # samples s..t-1 of the record from the window that starts i0 before them (their lags)
        got = model.predict_one_step([(u[s - i0:t], y[s - i0:t])], return_std=with_std)
        if with_std:
            mean[s - i0:t - i0], std[s - i0:t - i0] = got
        else:
            mean[s - i0:t - i0] = got
    return i0, mean, std


def one_step_check(model, u, y, lags: int = DEFAULT_LAGS, confidence: float = DEFAULT_CONFIDENCE,
                   with_std: bool = False) -> dict:
    """The one-step-ahead fit of a fitted ``GPNARX`` on the record (u, y) and the residual tests of its
    one-step residuals e = y - mean against the input (``residual_tests``), JSON-ready: ``n`` (one-step
    samples), ``fit`` [%] (eq. 14), ``rmse`` [output units], ``residual_tests``; with ``with_std`` also
    ``coverage`` [%] of the one-step band mean +- z std at ``confidence`` and ``z_rms``, the RMS of the
    standardised residuals e / std (about 1 for a calibrated one-step band)."""
    i0, mean, std = one_step_prediction(model, u, y, with_std=with_std)
    y1, u1 = np.asarray(y, float)[i0:], np.asarray(u, float)[i0:]
    e = y1 - mean
    out = {"n": int(e.size), "fit": fit_percent(y1, mean), "rmse": rmse(y1, mean)}
    if with_std:
        z = e / std
        out["coverage"] = 100.0 * float(np.mean(np.abs(z) <= band_z(confidence)))
        out["z_rms"] = rms(z)
    out["residual_tests"] = residual_tests(e, u1, lags, confidence)
    return out
