"""Validation report: paper-style figures, metrics JSON and a self-contained HTML page.

``report.html`` embeds its figures as ``data:`` PNG URIs (the PNG files are written next to it too),
so a copied or served report opens on its own.

Figures follow Teloli et al. (MSSP 2021), Figs. 2-10 and 15-20: (a) the full time response of
the measured data (dots) with the model mean and its (99 %) band, (b) a zoom, (c) the PSD of the
measured vs the predicted output and (d) the restoring force x displacement hysteresis loop.
Figs. 1 / 14 (the ny x nu x fit % lag surface) are drawn by :func:`lag_surface_figure`.

A *record* is a dict with keys

* ``name`` (str), ``role`` (e.g. "train", "validation", "test"), ``fs`` [Hz]
* ``t`` (optional, [s]; default ``arange(n) / fs``), ``u`` (input), ``y`` (measured output or None)
* ``y_clean`` (optional noise-free output), ``mean``, ``lower``, ``upper`` (model prediction)
* ``units`` ({"u": "N", "y": "m"}), ``metrics`` (dict of extra, already computed metrics)
* optional: ``zoom`` = (t0, t1) [s], ``drive_freq`` [Hz] (sine records: harmonic levels),
  ``psd`` = {"nperseg": 512 | None, "window": "hann" | "boxcar"}, ``freq_range`` = (f0, f1) [Hz],
  ``band_label`` (default "99% band").

``physics`` (optional) = {"mass": kg, "input_gain": 1.0, "output": "displacement" | "velocity"}.
"""
from __future__ import annotations

import base64
import html
import json
import math
import re
import tempfile
import threading
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpnarx.model import metrics as _metrics  # noqa: E402
from gpnarx.model import psd as _psd  # noqa: E402
from gpnarx.model.restoring import loop_area, loop_units, restoring_force  # noqa: E402
from gpnarx.training.lagchoice import edge_message, grid_edge  # noqa: E402

GP_NAME = "GP-NARX"
ZOOM_SECONDS = 0.25
PSD_NPERSEG = 512  # 2^9 Hann segments (paper, sine records)
N_HARMONICS = 3
N_PEAKS = 3
PSD_RANGE_DB = 120.0  # dynamic range shown in the PSD panel
_MAX_JSON_ARRAY = 64  # arrays longer than this are not written to report.json

_C_MEAS = "0.15"
_C_CLEAN = "tab:green"
_C_MEAN = "tab:red"
_C_BAND = "tab:blue"


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _arr(x):
    return None if x is None else np.asarray(x, dtype=float).ravel()


def _unpack(rec: dict) -> dict:
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


def _lab(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def _psd_opts(rec: dict, n: int) -> tuple[int | None, str]:
    opts = rec.get("psd") or {}
    nperseg = opts.get("nperseg", PSD_NPERSEG)
    if nperseg is not None and nperseg >= n:
        nperseg = None  # whole record when shorter than one segment
    return nperseg, opts.get("window", "hann")


def _db(p):
    return 10.0 * np.log10(np.maximum(np.asarray(p, float), 1e-300))


def _zoom_window(rec: dict, d: dict) -> tuple[float, float]:
    t = d["t"]
    if rec.get("zoom") is not None:
        t0, t1 = (float(v) for v in rec["zoom"])
        if t1 <= t0:
            raise ValueError(f"record {rec.get('name')!r}: zoom must be (t0, t1) with t1 > t0")
        return t0, t1
    ref = d["y"] if d["y"] is not None else d["mean"]
    ipk = int(np.nanargmax(np.abs(ref)))
    half = ZOOM_SECONDS / 2
    t0, t1 = t[ipk] - half, t[ipk] + half
    if t0 < t[0]:
        t0, t1 = t[0], t[0] + ZOOM_SECONDS
    if t1 > t[-1]:
        t0, t1 = max(t[0], t[-1] - ZOOM_SECONDS), t[-1]
    return float(t0), float(t1)


def _loop(u, y, fs, physics):
    """(x, R) for the hysteresis panel / loop area; None when physics has no mass."""
    if not physics or not physics.get("mass"):
        return None
    return restoring_force(u, y, fs, float(physics["mass"]), input_gain=float(physics.get("input_gain", 1.0)),
                           output=physics.get("output", "displacement"))


def _finite(v):
    """float or None (NaN / inf -> None)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _jsonable(o):
    """Recursively convert numpy / Path / tuples to JSON types; NaN and inf become None."""
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, np.ndarray):
        if o.size > _MAX_JSON_ARRAY:
            return {"omitted_array_shape": list(o.shape)}
        return [_jsonable(v) for v in o.tolist()]
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return _finite(o)
    if isinstance(o, Path):
        return str(o)
    if o is None or isinstance(o, str):
        return o
    return str(o)


def _slug(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    return s or "record"


# ----------------------------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------------------------
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
                out.append(_finite(band(x, fs, fk, half_width_hz=hw)))
            else:
                f, p = _psd.psd(x, fs, nperseg=None)
                sel = (f >= fk - hw) & (f <= fk + hw)
                out.append(_finite(10 * np.log10(np.sum(p[sel]) * (f[1] - f[0]) + 1e-300)) if sel.any() else None)
        except ValueError:
            out.append(None)
    return out


USES = {"training": "a training record (its rows trained the model)",
        "lag-selection": "a lag-selection record (the lag surface was judged on it)",
        "calibration": "a novelty-calibration record (healthy; the threshold was set on it)",
        "held-out": "a held-out record (used for no fit and no choice)"}


def record_use(roles) -> str | None:
    """A record's part in the study from its config roles: 'training' (role train, whatever else it
    is scored as, e.g. Bouc-Wen's verify 10/80 N sweeps), 'lag-selection' (lags), 'calibration'
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
    d = _unpack(rec)
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

    nperseg, window = _psd_opts(rec, n)
    fmin, fmax = rec.get("freq_range") or (0.0, None)
    if n >= 8:
        if d["y"] is not None:
            out["psd_peaks_measured"] = _psd.peak_frequencies(d["y"], fs, n_peaks=N_PEAKS, fmin=fmin, fmax=fmax,
                                                              nperseg=nperseg)
        out["psd_peaks_predicted"] = _psd.peak_frequencies(mean, fs, n_peaks=N_PEAKS, fmin=fmin, fmax=fmax,
                                                           nperseg=nperseg)

    if physics and physics.get("mass") and d["u"] is not None:
        out["loop_area_predicted"] = loop_area(*_loop(d["u"], mean, fs, physics))
        if d["y"] is not None:
            out["loop_area_measured"] = loop_area(*_loop(d["u"], d["y"], fs, physics))
        if d["y_clean"] is not None:
            out["loop_area_clean"] = loop_area(*_loop(d["u"], d["y_clean"], fs, physics))

    f0 = rec.get("drive_freq")
    if f0:
        f0 = float(f0)
        out["drive_freq"] = f0
        if d["y"] is not None:
            out["harmonics_db_measured"] = _harmonic_levels(d["y"], fs, f0, n)
        out["harmonics_db_predicted"] = _harmonic_levels(mean, fs, f0, n)
    return _jsonable(out)


# ----------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------
def _time_panel(ax, d, sel, band_label, dots):
    t = d["t"][sel]
    if d["lower"] is not None and d["upper"] is not None:
        ax.fill_between(t, d["lower"][sel], d["upper"][sel], color=_C_BAND, alpha=0.3, lw=0, label=band_label)
    if d["y"] is not None:
        if dots:
            ax.plot(t, d["y"][sel], ".", color=_C_MEAS, ms=2.5 if t.size < 2000 else 1.0, label="measured")
        else:
            ax.plot(t, d["y"][sel], "-", color=_C_MEAS, lw=0.5, label="measured")
    if d["y_clean"] is not None:
        ax.plot(t, d["y_clean"][sel], "-", color=_C_CLEAN, lw=0.6, alpha=0.8, label="noise-free")
    ax.plot(t, d["mean"][sel], "-", color=_C_MEAN, lw=0.8, label="model mean")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(_lab("y", d["uy"]))


def record_figure(rec: dict, physics: dict | None, path: Path) -> Path:
    """Four-panel PNG of one record (time, zoom, PSD, hysteresis loop); returns ``path``."""
    d = _unpack(rec)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fs, n = d["fs"], d["n"]
    band_label = rec.get("band_label", "99% band")
    fig, axs = plt.subplots(2, 2, figsize=(11, 7.5))
    (a, b), (c, e) = axs
    title = f"{rec.get('name', '')}" + (f" ({rec['role']})" if rec.get("role") else "")
    m = rec.get("metrics") or {}
    fit = m.get("fit")
    if fit is None and d["y"] is not None:
        fit = _metrics.fit_percent(d["y"], d["mean"])
    if _finite(fit) is not None:
        title += f" - fit {float(fit):.1f} %"
    fig.suptitle(title)

    # (a) full record
    _time_panel(a, d, slice(None), band_label, dots=n <= 20000)
    a.set_title("(a) time response")
    a.legend(loc="upper right", fontsize=7)

    # (b) zoom
    t0, t1 = _zoom_window(rec, d)
    sel = (d["t"] >= t0) & (d["t"] <= t1)
    if sel.sum() < 2:
        sel = slice(None)
    _time_panel(b, d, sel, band_label, dots=True)
    b.set_title(f"(b) zoom {t0:.3g}-{t1:.3g} s")

    # (c) PSD
    nperseg, window = _psd_opts(rec, n)
    if n >= 8:
        if d["y"] is not None:
            f, p = _psd.psd(d["y"], fs, nperseg=nperseg, window=window)
            c.plot(f, _db(p), "-", color=_C_MEAS, lw=0.9, label="measured")
        if d["y_clean"] is not None:
            f, p = _psd.psd(d["y_clean"], fs, nperseg=nperseg, window=window)
            c.plot(f, _db(p), "-", color=_C_CLEAN, lw=0.7, alpha=0.8, label="noise-free")
        f, p = _psd.psd(d["mean"], fs, nperseg=nperseg, window=window)
        c.plot(f, _db(p), "--", color=_C_MEAN, lw=0.9, label="model mean")
        if rec.get("freq_range"):
            c.set_xlim(*rec["freq_range"])
        levels = np.concatenate([np.asarray(ln.get_ydata(), float) for ln in c.lines
                                 if ln.get_label() in ("measured", "noise-free", "model mean")])
        levels = levels[np.isfinite(levels)]
        if levels.size:  # a noise-free mean can reach -300 dB: keep a 120 dB dynamic range
            top = float(levels.max())
            c.set_ylim(max(float(levels.min()), top - PSD_RANGE_DB) - 5.0, top + 5.0)
        if rec.get("drive_freq"):
            for k in range(1, N_HARMONICS + 1):
                if k * float(rec["drive_freq"]) < fs / 2:
                    c.axvline(k * float(rec["drive_freq"]), color="0.6", lw=0.5, ls=":")
        c.legend(loc="upper right", fontsize=7)
    seg = "whole record" if nperseg is None else f"{nperseg}-sample segments"
    c.set_title(f"(c) PSD ({window}, {seg})")
    c.set_xlabel("frequency [Hz]")
    c.set_ylabel(f"PSD [dB re {d['uy'] or 'unit'}$^2$/Hz]")

    # (d) hysteresis loop: against the noise-free response when it is known (the paper's Figs. 2-10
    # compare with the numerically integrated loop; R = g u - m y'' from a noisy y is mostly noise)
    if physics and physics.get("mass") and d["u"] is not None:
        if d["y_clean"] is not None:
            x, r = _loop(d["u"], d["y_clean"], fs, physics)
            e.plot(x, r, "-", color=_C_CLEAN, lw=0.6, label="noise-free")
        elif d["y"] is not None:
            x, r = _loop(d["u"], d["y"], fs, physics)
            e.plot(x, r, ".", color=_C_MEAS, ms=1.0, label="measured")
        x, r = _loop(d["u"], d["mean"], fs, physics)
        e.plot(x, r, "-", color=_C_MEAN, lw=0.5, label="model mean")
        lu = loop_units({"y": d["uy"]}, physics)  # R = g u - m x'' is a force [N] whatever u's unit (V)
        e.set_xlabel(_lab("displacement", lu["x"]))
        e.set_ylabel(_lab("restoring force", lu["force"]))
        e.set_title("(d) restoring force x displacement")
    elif d["u"] is not None:
        if d["y"] is not None:
            e.plot(d["y"], d["u"], ".", color=_C_MEAS, ms=1.0, label="measured")
        e.plot(d["mean"], d["u"], "-", color=_C_MEAN, lw=0.5, label="model mean")
        e.set_xlabel(_lab("y", d["uy"]))
        e.set_ylabel(_lab("u", d["uu"]))
        e.set_title("(d) input x output")
    else:
        e.text(0.5, 0.5, "no input signal", ha="center", va="center", transform=e.transAxes)
        e.set_title("(d) loop")
    if e.lines:
        e.legend(loc="upper left", fontsize=7)

    for ax in (a, b, c, e):
        ax.grid(True, lw=0.3, alpha=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _edges(v: np.ndarray) -> np.ndarray:
    if v.size == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = (v[1:] + v[:-1]) / 2
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def lag_surface_figure(surface: list[dict], chosen: tuple | None, paper: tuple | None, path: Path) -> Path:
    """Heat map of fit % over ny x nu (paper Figs. 1 / 14) with the chosen (and paper's) lags marked.

    ``surface``: list of {"ny", "nu", "fit"}; ``chosen``: (ny, nu) or {"ny", "nu"}; ``paper``: (ny, nu, fit),
    {"ny", "nu", "fit"} or None.
    Colour range: max(min fit, best - 30) .. best.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(paper, dict):
        paper = (paper.get("ny"), paper.get("nu"), paper.get("fit"))
    if isinstance(chosen, dict):
        chosen = (chosen["ny"], chosen["nu"])
    if not surface:
        raise ValueError("lag surface is empty")
    ny = np.array(sorted({int(r["ny"]) for r in surface}), float)
    nu = np.array(sorted({int(r["nu"]) for r in surface}), float)
    Z = np.full((ny.size, nu.size), np.nan)
    iy = {v: i for i, v in enumerate(ny)}
    iu = {v: i for i, v in enumerate(nu)}
    for r in surface:
        f = _finite(r.get("fit"))
        if f is not None:
            Z[iy[float(int(r["ny"]))], iu[float(int(r["nu"]))]] = f
    fig, ax = plt.subplots(figsize=(7, 5.5))
    if np.isfinite(Z).any():
        best, worst = float(np.nanmax(Z)), float(np.nanmin(Z))
        vmin = max(worst, best - 30.0)
        vmax = best if best > vmin else vmin + 1.0
    else:
        vmin, vmax = 0.0, 100.0
    mesh = ax.pcolormesh(_edges(nu), _edges(ny), np.ma.masked_invalid(Z), cmap="viridis", vmin=vmin, vmax=vmax,
                         shading="flat")
    fig.colorbar(mesh, ax=ax, label="fit [%]")
    if Z.size <= 144:
        for i in range(ny.size):
            for j in range(nu.size):
                if np.isfinite(Z[i, j]):
                    ax.text(nu[j], ny[i], f"{Z[i, j]:.1f}", ha="center", va="center", fontsize=6,
                            color="w" if Z[i, j] < (vmin + vmax) / 2 else "k")
    if chosen is not None:
        cy, cu = chosen[0], chosen[1]
        cf = next((r.get("fit") for r in surface if int(r["ny"]) == int(cy) and int(r["nu"]) == int(cu)), None)
        lab = f"chosen ny={cy}, nu={cu}" + (f" ({float(cf):.1f} %)" if _finite(cf) is not None else "")
        ax.plot([cu], [cy], "o", ms=11, mfc="none", mec="red", mew=2, label=lab)
    if paper is not None and paper[0] is not None and paper[1] is not None:
        py, pu = paper[0], paper[1]
        pf = paper[2] if len(paper) > 2 else None
        lab = f"paper ny={py}, nu={pu}" + (f" ({float(pf):.1f} %)" if _finite(pf) is not None else "")
        ax.plot([pu], [py], "X", ms=10, mfc="white", mec="k", label=lab)
    ax.set_xlabel("nu (input lags)")
    ax.set_ylabel("ny (output lags)")
    ax.set_title("Lag selection surface ny x nu x fit")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=8, framealpha=0.85)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------
# report
# ----------------------------------------------------------------------------------------------
def _norm_lag_surface(lag_surface, paper: dict | None):
    """(rows, chosen, paper_point) from a lag_surface dict (keys surface/table/grid, chosen, paper) or list."""
    if lag_surface is None:
        return None
    if isinstance(lag_surface, dict):
        rows = (lag_surface.get("surface") or lag_surface.get("cells") or lag_surface.get("table")
                or lag_surface.get("grid") or [])
        chosen = lag_surface.get("chosen")
        pp = lag_surface.get("paper")
    else:
        rows, chosen, pp = list(lag_surface), None, None
    rows = [{"ny": int(r["ny"]), "nu": int(r["nu"]), "fit": _finite(r.get("fit")),
             **({"error": r["error"]} if r.get("error") else {})} for r in rows]
    if pp is None and paper and paper.get("lags"):
        lg = paper["lags"]
        pp = (lg.get("ny"), lg.get("nu"), lg.get("fit"))
    if isinstance(pp, dict):
        pp = (pp.get("ny"), pp.get("nu"), pp.get("fit"))
    if pp is not None and (pp[0] is None or pp[1] is None):
        pp = None
    if chosen is None and rows:
        ok = [r for r in rows if r["fit"] is not None]
        if ok:
            bst = max(ok, key=lambda r: r["fit"])
            chosen = (bst["ny"], bst["nu"])
    if isinstance(chosen, dict):
        chosen = (chosen["ny"], chosen["nu"])
    return rows, (tuple(int(v) for v in chosen[:2]) if chosen is not None else None), (tuple(pp) if pp else None)


def _best_cell(rows: list[dict]) -> dict | None:
    """The lag-surface row with the highest finite fit (None when no row has one)."""
    return max((r for r in rows if r["fit"] is not None), key=lambda r: r["fit"], default=None)


def _lag_edge(rows: list[dict]) -> list[str]:
    """Lag axes on which the best row sits at the largest value tried (training.lagchoice.grid_edge)."""
    best = _best_cell(rows)
    return grid_edge(best, [r["ny"] for r in rows], [r["nu"] for r in rows]) if best else []


def _fmt(v, nd=3) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            return "&ndash;"
        if f != 0 and (abs(f) >= 1e5 or abs(f) < 1e-3):
            return f"{f:.{nd}e}"
        return f"{f:.{nd}g}" if abs(f) < 1 else f"{f:.{max(1, nd - 1)}f}" if abs(f) < 1e3 else f"{f:.0f}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x, nd) for x in v)
    if isinstance(v, dict):
        return "; ".join(f"{html.escape(str(k))}: {_fmt(x, nd)}" for k, x in v.items())
    return html.escape(str(v))


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and all(not isinstance(x, dict) for x in v.values()) and len(v) > 6:
            out.append((key, v))
        elif isinstance(v, dict):
            out.extend(_flatten(v, key + "."))
        else:
            out.append((key, v))
    return out


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1200px;
color:#222;padding:0 1em}
h1{font-size:1.6em;border-bottom:2px solid #446;padding-bottom:.2em}
h2{font-size:1.25em;margin-top:1.6em;color:#335}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em}
th,td{border:1px solid #ccd;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#eef0f6}
td.l,th.l{text-align:left}
tr:nth-child(even) td{background:#f8f9fc}
td.best{font-weight:bold;background:#e3f4e3 !important}
figure{margin:1em 0;border:1px solid #dde;padding:.5em}
figure img{max-width:100%;height:auto}
figcaption{font-size:.9em;color:#444}
.note{font-size:.85em;color:#555}
"""


def _table(header: list[str], rows: list[list[str]], left_cols: int = 1) -> str:
    h = "".join(f'<th class="{"l" if i < left_cols else ""}">{html.escape(c)}</th>' for i, c in enumerate(header))
    body = []
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            cls = "l" if i < left_cols else ""
            if isinstance(c, tuple):  # (text, extra class)
                c, extra = c
                cls = (cls + " " + extra).strip()
            cells.append(f'<td class="{cls}">{c}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{h}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _png_data_uri(path: Path) -> str:
    """A PNG file as a ``data:`` URI, so the HTML page opens on its own (copied, mailed, served)."""
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _img(fn: str, alt: str, embedded: dict) -> str:
    """``<img>`` of figure ``fn``: embedded as a data URI when given, the file name kept in data-file."""
    esc = html.escape
    src = embedded.get(fn, fn)
    return f"<img src='{esc(src)}' data-file='{esc(fn)}' alt='{esc(alt)}'>"


def _html(title, summary, rec_entries, lag, baselines_tab, paper, fig_names, lag_png, embedded=None) -> str:
    esc = html.escape
    embedded = embedded or {}
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
             f"<style>{_CSS}</style></head><body>", f"<h1>{esc(title)}</h1>"]

    # summary
    parts.append("<h2>Summary</h2>")
    srows = [[esc(k), _fmt(v)] for k, v in _flatten(summary or {})]
    if lag is not None:
        rows, chosen, pp = lag
        if chosen is not None:
            cf = next((r["fit"] for r in rows if (r["ny"], r["nu"]) == chosen), None)
            fit_note = f" (fit {_fmt(cf)} %)" if cf is not None else ""
            srows.append(["chosen lags (ny, nu)", f"{chosen[0]}, {chosen[1]}{fit_note}"])
        if pp is not None:
            srows.append(["paper lags (ny, nu)", f"{_fmt(pp[0])}, {_fmt(pp[1])}"
                          + (f" (fit {_fmt(pp[2])} %)" if len(pp) > 2 and pp[2] is not None else "")])
        edge = _lag_edge(rows)
        if edge:
            srows.append(["lag grid edge", esc(edge_message({"best": _best_cell(rows), "edge": edge}))])
    if srows:
        parts.append(_table(["item", "value"], srows))
    else:
        parts.append("<p class='note'>No summary values.</p>")

    # per-record metrics
    parts.append("<h2>Per-record metrics</h2>")
    paper_recs = (paper or {}).get("records") or {}
    has_paper = any(e["name"] in paper_recs for e in rec_entries)
    has_clean = any("fit_clean" in e["metrics"] for e in rec_entries)
    has_use = any(e["metrics"].get("use") for e in rec_entries)
    head = ["record"] + (["use"] if has_use else []) + ["role", "n", "fit [%]"] + \
        (["paper fit [%]"] if has_paper else []) + \
        ["RMSE", "NRMSE", "coverage [%]", "band width"] + \
        (["fit clean [%]", "coverage latent [%]"] if has_clean else [])
    rows = []
    for e in rec_entries:
        m = e["metrics"]
        unit = esc(e.get("units", {}).get("y", ""))
        r = [esc(e["name"])] + ([esc(str(m.get("use") or ""))] if has_use else []) + \
            [esc(str(e.get("role", ""))), _fmt(m.get("n_samples")), _fmt(m.get("fit"))]
        if has_paper:
            r.append(_fmt((paper_recs.get(e["name"]) or {}).get("fit")))
        r += [_fmt(m.get("rmse")) + (f" {unit}" if m.get("rmse") is not None and unit else ""),
              _fmt(m.get("nrmse")), _fmt(m.get("coverage")),
              _fmt(m.get("band_width")) + (f" {unit}" if m.get("band_width") is not None and unit else "")]
        if has_clean:
            # a report written before the latent band kept the predictive band's coverage_clean
            r += [_fmt(m.get("fit_clean")), _fmt(m.get("coverage_latent"))]
        rows.append(r)
    parts.append(_table(head, rows, left_cols=3 if has_use else 2))
    parts.append("<p class='note'>Use: training (the record's rows trained the model; Bouc-Wen's verify 10/80 N "
                 "sweeps are the training records), lag-selection (the lag surface was judged on it), calibration "
                 "(healthy records that set the novelty threshold), held-out (used for no fit and no choice). "
                 "Coverage: % of measured samples inside the predictive band (noise &sigma;<sub>y</sub><sup>2</sup> "
                 "included). Coverage latent: % of noise-free samples (simulated systems) inside the latent band "
                 "(the same confidence without the noise term).</p>")

    # spectral / physics
    has_clean_loop = any("loop_area_clean" in e["metrics"] for e in rec_entries)
    head = ["record", "PSD peaks measured [Hz]", "PSD peaks predicted [Hz]", "loop area measured [J]"] + \
        (["loop area noise-free [J]"] if has_clean_loop else []) + \
        ["loop area predicted [J]", "drive [Hz]", "harmonics 1-3 measured [dB]", "harmonics 1-3 predicted [dB]"]
    rows = []
    for e in rec_entries:
        m = e["metrics"]
        rows.append([esc(e["name"]), _fmt(m.get("psd_peaks_measured")), _fmt(m.get("psd_peaks_predicted")),
                     _fmt(m.get("loop_area_measured"))] + ([_fmt(m.get("loop_area_clean"))] if has_clean_loop else [])
                    + [_fmt(m.get("loop_area_predicted")), _fmt(m.get("drive_freq")),
                       _fmt(m.get("harmonics_db_measured")), _fmt(m.get("harmonics_db_predicted"))])
    parts.append("<h2>Spectra and hysteresis</h2>")
    parts.append(_table(head, rows))

    # other metrics supplied by the caller
    extra_keys = sorted({k for e in rec_entries for k, v in e.get("extra_metrics", {}).items()
                         if not isinstance(v, (dict, list))})
    if extra_keys:
        parts.append("<h2>Additional metrics</h2>")
        rows = [[esc(e["name"])] + [_fmt(e.get("extra_metrics", {}).get(k)) for k in extra_keys] for e in rec_entries]
        parts.append(_table(["record"] + extra_keys, rows))

    # baselines
    if baselines_tab:
        models = baselines_tab["models"]
        parts.append("<h2>GP-NARX vs baselines (fit %)</h2>")
        rows = []
        for rname, fits in baselines_tab["rows"].items():
            vals = [_finite(fits.get(mn)) for mn in models]
            ok = [v for v in vals if v is not None]
            best = max(ok) if ok else None
            cells = [esc(rname)]
            for v in vals:
                cells.append((_fmt(v), "best") if v is not None and v == best else _fmt(v))
            winners = [mn for mn, v in zip(models, vals) if v is not None and v == best]
            cells.append(esc(", ".join(winners)) if winners else "&ndash;")
            rows.append(cells)
        parts.append(_table(["record"] + models + ["best"], rows))
        parts.append("<p class='note'>Highest fit per record in bold. Fit is eq. (14): "
                     "100 (1 - ||y - &mu;|| / ||y||).</p>")

    # figures
    parts.append("<h2>Figures</h2>")
    if lag_png:
        parts.append(f"<figure>{_img(lag_png, 'lag surface', embedded)}<figcaption>Lag selection surface "
                     f"n<sub>y</sub> &times; n<sub>u</sub> &times; fit % (paper Figs. 1 / 14).</figcaption></figure>")
    for e in rec_entries:
        fn = fig_names.get(e["name"])
        if fn:
            parts.append(f"<figure>{_img(fn, e['name'], embedded)}<figcaption>"
                         f"<b>{esc(e['name'])}</b> ({esc(str(e.get('role', '')))}): (a) time response, measured "
                         f"(dots), model mean and {esc(e.get('band_label', '99% band'))}; (b) zoom; (c) PSD; "
                         f"(d) hysteresis loop.</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)


_FIGURE_LOCK = threading.Lock()  # pyplot's state is per process: one figure at a time per worker process


def render_record(rec: dict, physics: dict | None) -> tuple[dict, bytes]:
    """One record's computed metrics and its figure as PNG bytes: the report's per-record work as one
    task (a Dask worker runs it on the record sent to it; the client writes the files)."""
    computed = record_metrics(rec, physics)
    merged = {**_jsonable(rec.get("metrics") or {}), **computed}
    with _FIGURE_LOCK, tempfile.TemporaryDirectory() as tmp:
        png = record_figure(dict(rec, metrics=merged), physics, Path(tmp) / "record.png")
        return computed, png.read_bytes()


def write_report(out_dir: Path, title: str, summary: dict, records: list[dict], physics: dict | None = None,
                 lag_surface: dict | None = None, baselines: dict | None = None, paper: dict | None = None,
                 runner=None) -> dict:
    """Write report.json, one PNG per record, lag_surface.png (if given) and report.html to ``out_dir``.

    ``lag_surface``: {"surface" (or "cells"): [{"ny", "nu", "fit"}...], "chosen": (ny, nu) or {"ny", "nu"},
    "paper": (ny, nu, fit) or {"ny", "nu", "fit"}} (training.lags.lag_surface output works as is)
    (a plain list of rows is accepted; ``paper["lags"]`` supplies the paper's point when absent).
    ``baselines``: {record_name: {model_name: {"fit": .., "rmse": ..}}}.
    ``paper``: {"lags": {"ny", "nu", "fit"}, "records": {record_name: {"fit": ..}}}.

    ``runner`` (a ``training.distributed.TaskRunner`` on a Dask cluster): each record's metrics and
    figure are computed as a task (:func:`render_record`); the files are written here all the same.

    Returns {"json": Path, "html": Path, "lag_surface": Path | None, "records": {name: Path}}.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict = {"records": {}, "lag_surface": None}

    rendered = None
    if runner is not None and runner.distributed:
        rendered = runner.run(render_record, [(runner.send(rec), physics) for rec in records])
    rec_entries, fig_names, used = [], {}, set()
    for i, rec in enumerate(records):
        name = str(rec.get("name", f"record{i}"))
        computed = record_metrics(rec, physics) if rendered is None else rendered[i][0]
        given = _jsonable(rec.get("metrics") or {})
        merged = {**given, **computed}
        extra = {k: v for k, v in given.items() if k not in computed}
        fn = f"record_{_slug(name)}.png"
        k = 2
        while fn in used:
            fn = f"record_{_slug(name)}_{k}.png"
            k += 1
        used.add(fn)
        if rendered is None:
            paths["records"][name] = record_figure(dict(rec, metrics=merged), physics, out_dir / fn)
        else:
            (out_dir / fn).write_bytes(rendered[i][1])
            paths["records"][name] = out_dir / fn
        fig_names[name] = fn
        rec_entries.append({"name": name, "role": rec.get("role"), "fs": _finite(rec.get("fs")),
                            "units": dict(rec.get("units") or {}), "figure": fn, "metrics": merged,
                            "extra_metrics": extra, "band_label": rec.get("band_label", "99% band")})

    lag = _norm_lag_surface(lag_surface, paper)
    lag_png = None
    if lag is not None and lag[0]:
        paths["lag_surface"] = lag_surface_figure(lag[0], lag[1], lag[2], out_dir / "lag_surface.png")
        lag_png = "lag_surface.png"

    # baselines side by side with GP-NARX
    baselines_json = _jsonable(baselines or {})
    baselines_tab = None
    if baselines:
        models = [GP_NAME] + sorted({mn for v in baselines.values() for mn in (v or {})} - {GP_NAME})
        rows = {}
        gp_fit = {e["name"]: e["metrics"].get("fit") for e in rec_entries}
        for rname in list(gp_fit) + [r for r in baselines if r not in gp_fit]:
            fits = {GP_NAME: gp_fit.get(rname)}
            for mn, mv in (baselines.get(rname) or {}).items():
                fits[mn] = mv.get("fit") if isinstance(mv, dict) else mv
            if rname in baselines or fits[GP_NAME] is not None:
                rows[rname] = fits
        baselines_tab = {"models": models, "rows": rows}

    report = {
        "title": title,
        "summary": _jsonable(summary or {}),
        "physics": _jsonable(physics) if physics else None,
        "records": [{k: v for k, v in e.items() if k not in ("extra_metrics", "band_label")} for e in rec_entries],
        "lag_surface": None if lag is None else {
            "table": lag[0], "chosen": list(lag[1]) if lag[1] else None,
            "paper": _jsonable(list(lag[2])) if lag[2] else None,
            "best": _jsonable(_best_cell(lag[0])),
            "edge": _lag_edge(lag[0]),
            "figure": lag_png},
        "baselines": baselines_json,
        "comparison": None if baselines_tab is None else _jsonable(
            {r: {**f, "best": max((m for m in f if _finite(f[m]) is not None), key=lambda m: f[m], default=None)}
             for r, f in baselines_tab["rows"].items()}),
        "paper": _jsonable(paper) if paper else None,
    }
    report = _jsonable(report)
    jpath = out_dir / "report.json"
    jpath.write_text(json.dumps(report, indent=2, allow_nan=False))
    paths["json"] = jpath

    # figures embedded as data URIs: the page is self-contained (the PNG files stay for other uses)
    embedded = {fn: _png_data_uri(out_dir / fn) for fn in [*fig_names.values(), *([lag_png] if lag_png else [])]}
    hpath = out_dir / "report.html"
    hpath.write_text(_html(title, report["summary"], rec_entries, lag, baselines_tab, paper, fig_names, lag_png,
                           embedded), encoding="utf-8")
    paths["html"] = hpath
    return paths
