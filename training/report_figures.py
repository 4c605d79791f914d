"""Paper-style figures of a validation report (Teloli et al., MSSP 2021, Figs. 2-10 and 15-20): the time
response with the model mean and band, a zoom, the PSDs and the hysteresis loop of one record; and the lag
surface heat map (Figs. 1 / 14)."""
from __future__ import annotations

import threading
from pathlib import Path

try:
    import matplotlib
except ImportError:  # the core install serves and predicts without it; training reports need it
    raise ImportError("training reports and figures need matplotlib: pip install 'gpnarx[train]'") from None

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpnarx.model import metrics as _metrics  # noqa: E402
from gpnarx.model import psd as _psd  # noqa: E402
from gpnarx.model.restoring import loop_units  # noqa: E402
from gpnarx.training.report_metrics import (  # noqa: E402
    N_HARMONICS,
    finite_or_none,
    loop_of,
    psd_options,
    unpack_record,
)

ZOOM_SECONDS = 0.25
PSD_RANGE_DB = 120.0  # dynamic range shown in the PSD panel
_C_MEAS = "0.15"
_C_CLEAN = "tab:green"
_C_MEAN = "tab:red"
_C_BAND = "tab:blue"


def _lab(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


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
    d = unpack_record(rec)
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
    if finite_or_none(fit) is not None:
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
    nperseg, window = psd_options(rec, n)
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
            x, r = loop_of(d["u"], d["y_clean"], fs, physics)
            e.plot(x, r, "-", color=_C_CLEAN, lw=0.6, label="noise-free")
        elif d["y"] is not None:
            x, r = loop_of(d["u"], d["y"], fs, physics)
            e.plot(x, r, ".", color=_C_MEAS, ms=1.0, label="measured")
        x, r = loop_of(d["u"], d["mean"], fs, physics)
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


def cell_box(nu: np.ndarray, ny: np.ndarray, cu, cy, inset: float = 0.0) -> tuple | None:
    """(x0, y0, width, height) of the heat map's cell (nu=cu, ny=cy) in data units, shrunk by ``inset`` (a
    fraction of the cell on each side); None when (cu, cy) is not a cell of the grid."""
    j = np.flatnonzero(nu == float(cu))
    i = np.flatnonzero(ny == float(cy))
    if not (i.size and j.size):
        return None
    xe, ye = _edges(nu), _edges(ny)
    x0, x1, y0, y1 = xe[j[0]], xe[j[0] + 1], ye[i[0]], ye[i[0] + 1]
    dx, dy = inset * (x1 - x0), inset * (y1 - y0)
    return float(x0 + dx), float(y0 + dy), float(x1 - x0 - 2 * dx), float(y1 - y0 - 2 * dy)


def _mark_cell(ax, nu, ny, cu, cy, label: str, edge: dict, marker: dict, inset: float) -> None:
    from matplotlib.patches import Rectangle

    box = cell_box(nu, ny, cu, cy, inset)
    if box is None:
        ax.plot([cu], [cy], ls="none", ms=10, mfc="none", mew=2, label=label, **marker)
    else:
        ax.add_patch(Rectangle(box[:2], box[2], box[3], fill=False, label=label, zorder=3, **edge))


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
        f = finite_or_none(r.get("fit"))
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
    # the chosen and the paper's cells are outlined along the cell's edges, so the cell's own fit label stays
    # readable (a marker at the centre covered it); a cell off the grid gets a marker at its (nu, ny)
    if chosen is not None:
        cy, cu = chosen[0], chosen[1]
        cf = next((r.get("fit") for r in surface if int(r["ny"]) == int(cy) and int(r["nu"]) == int(cu)), None)
        lab = f"chosen ny={cy}, nu={cu}" + (f" ({float(cf):.1f} %)" if finite_or_none(cf) is not None else "")
        _mark_cell(ax, nu, ny, cu, cy, lab, dict(edgecolor="red", linewidth=2.5), dict(marker="o", mec="red"), 0.0)
    if paper is not None and paper[0] is not None and paper[1] is not None:
        py, pu = paper[0], paper[1]
        pf = paper[2] if len(paper) > 2 else None
        lab = f"paper ny={py}, nu={pu}" + (f" ({float(pf):.1f} %)" if finite_or_none(pf) is not None else "")
        _mark_cell(ax, nu, ny, pu, py, lab, dict(edgecolor="k", linewidth=1.5, linestyle="--"),
                   dict(marker="X", mec="k"), 0.12)
    ax.set_xlabel("nu (input lags)")
    ax.set_ylabel("ny (output lags)")
    ax.set_title("Lag selection surface ny x nu x fit")
    if ax.get_legend_handles_labels()[0]:  # below the axes: over the map it would hide cells' labels
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------
# report


FIGURE_LOCK = threading.Lock()  # pyplot's state is per process: one figure at a time per worker process


def receptance_figure(runs: list[dict], path: Path, f_range=(5.0, 40.0)) -> Path:
    """The receptance FRFs of several sweeps on one log axis (the paper's Fig. 12(a)): ``runs`` as
    ``studies.frf_check.sweep_receptances`` returns them (freq [Hz], receptance [m/V], name, peak_freq)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for r in runs:
        sel = (r["freq"] >= f_range[0]) & (r["freq"] <= f_range[1])
        ax.semilogy(r["freq"][sel], r["receptance"][sel], lw=1.0,
                    label=f"{r['name']} (peak {r['peak_freq']:.2f} Hz)")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("receptance |X/V| [m/V]")
    ax.set_title("Real BERT rig, 5 N m: receptance of the swept sines (LMS FRF)")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def residual_figure(check: dict, name: str, path: Path) -> Path:
    """The residual tests of one record (``model.residual_tests.one_step_check``'s dict): (a) the one-step
    residuals' autocorrelation at lags 1..L and (b) their cross-correlation with the input at -L..L, as stems,
    with the confidence limits +-z / sqrt(N) dashed and the lags outside them in red."""
    tests = check["residual_tests"]
    limit = float(tests["limit"])
    conf = 100.0 * float(tests["confidence"])
    panels = [("autocorrelation", "(a) autocorrelation of e", "lag k [samples]", "r_e(k)", "ljung_box",
               "Ljung-Box")]
    if tests.get("cross_correlation"):
        panels.append(("cross_correlation", "(b) cross-correlation of u and e", "lag k [samples] (u leads e for k > 0)",
                       "r_ue(k)", "portmanteau", "portmanteau"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 3.4), squeeze=False)
    for ax, (key, title, xlabel, ylabel, test, test_name) in zip(axes[0], panels):
        part = tests[key]
        lag = np.asarray(part["lag"], float)
        r = np.array([np.nan if v is None else v for v in part["r"]], float)
        out = np.abs(r) > limit
        ax.vlines(lag[~out], 0.0, r[~out], color=_C_BAND, lw=1.2)
        ax.vlines(lag[out], 0.0, r[out], color=_C_MEAN, lw=1.6)
        ax.plot(lag, r, ls="none", marker="o", ms=2.5, color="k")
        ax.axhline(0.0, color="0.3", lw=0.6)
        for s in (-1.0, 1.0):
            ax.axhline(s * limit, color="0.2", ls="--", lw=0.9)
        share = finite_or_none(part["outside_share"])
        p = finite_or_none(part[test]["p_value"])
        ax.set_title(f"{title}\n{part['n_outside']} of {lag.size} lags outside"
                     + (f" ({100 * share:.0f} %)" if share is not None else "")
                     + ("" if p is None else f", {test_name} p = {p:.2g}" if p > 0 else f", {test_name} p < 1e-300"),
                     fontsize=8.5)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, lw=0.3)
    fig.suptitle(f"{name}: one-step residuals (N = {tests['n']}, one-step fit {check['fit']:.1f} %), "
                 f"{conf:g} % limits +-{limit:.3g}", fontsize=9.5)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
