"""Baselines a system-identification user fits first, on the same records as the GP-NARX.

* ``LinearARX``: least-squares ARX with the same regressors as eq. (3) (same ny, nu), free-run
  simulated (model predicted output) from rest or from the first ny measured outputs.
* ``FrolsNARX``: a polynomial NARX from SysIdentPy (FROLS structure selection, degree 2, AIC,
  least squares), as a new user of that library would fit it: training records concatenated,
  ``ylag = ny``, ``xlag = nu`` (capped at ``max_lag`` to keep the candidate set tractable),
  free-run with ``predict(X=u, y=y[:max_lag])``. Optional: needs the ``baselines`` extra.
"""
from __future__ import annotations

import time

import numpy as np

from gpnarx.model.metrics import fit_percent, rmse
from gpnarx.model.regressors import stack_regressors
from gpnarx.training.lagchoice import choose_lags


class LinearARX:
    """y_i = a . [y_{i-1..i-ny}] + b . [u_i..u_{i-nu+1}] by least squares."""

    name = "linear ARX"

    def __init__(self, ny: int, nu: int):
        self.ny, self.nu = int(ny), int(nu)

    def fit(self, records) -> "LinearARX":
        t0 = time.perf_counter()
        X, Y, _ = stack_regressors([(r.u, r.y) for r in records], self.ny, self.nu)
        self.coef_ = np.linalg.lstsq(X, Y, rcond=None)[0]
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def simulate(self, u, y0=None) -> np.ndarray:
        """Free-run output for input u (from rest, or from y0 = first ny outputs)."""
        ny, nu = self.ny, self.nu
        a, b = self.coef_[:ny], self.coef_[ny:]
        n = u.size
        upad = np.concatenate([np.zeros(nu - 1), u])
        uterm = np.convolve(upad, b, mode="valid")[:n]  # sum_j b_j u_{i-j}
        y = np.zeros(n + ny)
        i0 = 0
        if y0 is not None:
            i0 = ny
            y[ny:2 * ny] = np.asarray(y0, float)[:ny]
        for i in range(i0, n):  # y[ny + i] is y_i; y[i : ny + i] reversed is [y_{i-1}, ..., y_{i-ny}]
            y[ny + i] = float(np.dot(a, y[i : ny + i][::-1])) + uterm[i]
        return y[ny:]


#: fit points (eq. 14) within which two cells of ``arx_lag_search`` are a tie, decided by fewer lags: round-off
#: only (two exact orders differ by about 1e-12 points from one BLAS to another), so the baseline stays the
#: best ARX of the grid rather than the GP-NARX rule's smallest cell within 0.5 points
ARX_TIE_TOLERANCE = 1e-6


def arx_lag_search(train_records, lag_records, ny_grid, nu_grid, criterion: str = "worst") -> dict:
    """The ARX a system-identification engineer would choose with the GP-NARX's own lag search: at each
    (ny, nu) of the grid, least squares on ``train_records``, free-run on each ``lag_records`` record
    (from rest, or from its first ny measured outputs when ``meta["initial"] == "measured"``), scored by
    fit % (eq. 14); the cell with the best ``criterion`` ("worst": the lowest record fit, "mean": the
    mean fit) is refitted and returned. Cells within ``ARX_TIE_TOLERANCE`` points of the best are ties:
    the smallest ny + nu among them wins (``lagchoice.choose_lags``' rule), then the higher fit.

    Returns ``{"model": LinearARX, "ny", "nu", "fit", "cells": [{"ny", "nu", "fits"}...]}``.
    """
    if criterion not in ("worst", "mean"):
        raise ValueError(f"criterion must be 'worst' or 'mean', got {criterion!r}")
    cells = []
    for ny in ny_grid:
        for nu in nu_grid:
            arx = LinearARX(int(ny), int(nu)).fit(train_records)
            fits = {}
            for rec in lag_records:
                y0 = rec.y[: arx.ny] if rec.meta.get("initial") == "measured" else None
                with np.errstate(all="ignore"):
                    f = fit_percent(rec.y, arx.simulate(rec.u, y0=y0))
                fits[rec.name] = float(f) if np.isfinite(f) else -np.inf
            cells.append({"ny": int(ny), "nu": int(nu), "fits": fits})
    if not cells:
        raise ValueError("the ARX lag search needs at least one (ny, nu) cell")

    def score(c):
        vals = list(c["fits"].values())
        return min(vals) if criterion == "worst" else float(np.mean(vals))

    scored = [{"ny": c["ny"], "nu": c["nu"], "fit": score(c), "cell": c} for c in cells]
    if any(np.isfinite(c["fit"]) for c in scored):
        best = choose_lags(scored, tolerance=ARX_TIE_TOLERANCE)["cell"]
    else:  # every cell diverged: the fewest lags
        best = min(cells, key=lambda c: c["ny"] + c["nu"])
    return {"model": LinearARX(best["ny"], best["nu"]).fit(train_records), "ny": best["ny"], "nu": best["nu"],
            "fit": score(best), "criterion": criterion,
            "cells": [{**c, "fits": {k: (v if np.isfinite(v) else None) for k, v in c["fits"].items()}}
                      for c in cells]}


class FrolsNARX:
    """SysIdentPy polynomial NARX (FROLS), degree 2, AIC-selected terms."""

    name = "polynomial NARX (SysIdentPy FROLS)"

    def __init__(self, ny: int, nu: int, degree: int = 2, max_lag: int = 10, n_info_values: int = 25):
        self.ny, self.nu = min(int(ny), max_lag), min(int(nu), max_lag)
        self.degree, self.n_info_values = degree, n_info_values

    @staticmethod
    def available() -> bool:
        try:
            import sysidentpy  # noqa: F401
        except ImportError:
            return False
        return True

    def fit(self, records) -> "FrolsNARX":
        from sysidentpy.basis_function import Polynomial
        from sysidentpy.model_structure_selection import FROLS
        from sysidentpy.parameter_estimation import LeastSquares

        t0 = time.perf_counter()
        u = np.concatenate([r.u for r in records])[:, None]
        y = np.concatenate([r.y for r in records])[:, None]
        self.scale_u_, self.scale_y_ = float(np.std(u)) or 1.0, float(np.std(y)) or 1.0
        self.model_ = FROLS(order_selection=True, n_info_values=self.n_info_values, ylag=self.ny, xlag=self.nu,
                            info_criteria="aic", estimator=LeastSquares(),
                            basis_function=Polynomial(degree=self.degree), model_type="NARMAX")
        self.model_.fit(X=u / self.scale_u_, y=y / self.scale_y_)
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def simulate(self, u, y0=None) -> np.ndarray:
        lag = max(self.ny, self.nu)
        init = np.zeros(lag) if y0 is None else np.r_[np.asarray(y0, float), np.zeros(lag)][:lag]
        yh = self.model_.predict(X=(np.asarray(u, float) / self.scale_u_)[:, None],
                                 y=(init / self.scale_y_)[:, None])
        out = np.asarray(yh, float).ravel()[: u.size] * self.scale_y_
        if not np.all(np.isfinite(out)):  # a diverging simulation scores as a zero prediction
            out = np.where(np.isfinite(out), out, 0.0)
            out = np.clip(out, -1e6 * self.scale_y_, 1e6 * self.scale_y_)
        return out


def fit_baselines(train_records, ny: int, nu: int, log=None) -> dict:
    """Fitted baselines by name (SysIdentPy only when installed)."""
    out = {"linear ARX": LinearARX(ny, nu).fit(train_records)}
    if FrolsNARX.available():
        try:
            out["polynomial NARX (FROLS)"] = FrolsNARX(ny, nu).fit(train_records)
        except Exception as exc:  # a third-party failure must not stop the report
            if log:
                log(f"SysIdentPy FROLS baseline failed: {exc}")
    elif log:
        log("SysIdentPy not installed (pip install -e '.[baselines]'): polynomial NARX baseline skipped")
    return out


def score_baselines(baselines: dict, records, initial_ny: dict | None = None) -> dict:
    """{record_name: {baseline_name: {fit, rmse, fit_clean?}}} on free-run simulations."""
    res = {}
    for rec in records:
        row = {}
        for bname, b in baselines.items():
            y0 = rec.y[: b.ny] if rec.meta.get("initial") == "measured" else None
            try:
                yhat = b.simulate(rec.u, y0=y0)
                m = {"fit": fit_percent(rec.y, yhat), "rmse": rmse(rec.y, yhat)}
                if rec.meta.get("clean_y") is not None:
                    m["fit_clean"] = fit_percent(rec.meta["clean_y"], yhat)
            except Exception as exc:  # noqa: BLE001 - report, do not crash the protocol
                m = {"fit": None, "error": str(exc)}
            row[bname] = m
        res[rec.name] = row
    return res
