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

The figures need matplotlib (the extra ``train``). Without it (the core install, e.g. the default bundles
built on first use) the report is written without them: report.json and report.html with every table, and a
note on the page saying why the figures are missing and how to get them (``FIGURES_MISSING``).
"""
from __future__ import annotations

import base64
import html
import json
import math
import tempfile
import threading
from pathlib import Path

import numpy as np

from gpnarx.training.lagchoice import edge_message, grid_edge
from gpnarx.training.report_metrics import (
    finite_or_none,
    record_metrics,
    slug,
    to_report_json,
)

try:
    from gpnarx.training.report_figures import FIGURE_LOCK, lag_surface_figure, record_figure, residual_figure
except ImportError:  # the core install: reports without figures
    FIGURE_LOCK, lag_surface_figure, record_figure, residual_figure = threading.Lock(), None, None, None

GP_NAME = "GP-NARX"
#: why a report has no figures, and how to get them (report.json ``figures_missing``, the page's note)
FIGURES_MISSING = ("matplotlib is not installed where this report was written (the core install); "
                   "pip install 'gpnarx[train]', then train again to get a report with figures")
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
    rows = [{"ny": int(r["ny"]), "nu": int(r["nu"]), "fit": finite_or_none(r.get("fit")),
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


def _trained_checks(rec_entries) -> str:
    """The part of the use note naming the scored records that also trained the model (their config roles),
    or '' when none did."""
    by_role: dict = {}
    for e in rec_entries:
        if e["metrics"].get("use") == "training" and e.get("role") and e.get("role") != "train":
            by_role.setdefault(str(e["role"]), []).append(str(e["name"]))
    if not by_role:
        return ""
    said = []
    for role, names in by_role.items():
        listed = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
        verb = "is a training record" if len(names) == 1 else "are training records"
        said.append(f"{html.escape(listed)} ({html.escape(role)}) {verb}")
    return "; here " + "; ".join(said)


def _html(title, summary, rec_entries, lag, baselines_tab, paper, fig_names, lag_png, embedded=None,
          missing: str | None = None) -> str:
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
    parts.append("<p class='note'>Use: training (the record's rows trained the model" + _trained_checks(rec_entries)
                 + "), lag-selection (the lag surface was judged on it), calibration "
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
            vals = [finite_or_none(fits.get(mn)) for mn in models]
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

    parts += _residual_section(rec_entries, embedded)

    # figures
    parts.append("<h2>Figures</h2>")
    if missing:
        parts.append(f"<p class='note missing-figures'>No figures: {esc(missing)}.</p>")
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


def _residual_section(rec_entries, embedded: dict) -> list[str]:
    """The page's residual tests (records with ``residual_tests``, ``training.report_residuals``): a table of
    the one-step fit, the share of lags outside the limits and the tests' p-values, and each record's figure."""
    esc = html.escape
    tested = [e for e in rec_entries if e.get("residual_tests")]
    if not tested:
        return []
    parts = ["<h2>Residual tests</h2>"]
    rows, lags, conf = [], None, None
    for e in tested:
        c = e["residual_tests"]
        head = [esc(e["name"]), esc(str(e.get("role", "")))]
        if c.get("error"):
            rows.append(head + [f"not tested: {esc(c['error'])}"] + ["&ndash;"] * 7)
            continue
        t = c["residual_tests"]
        lags, conf = t["lags"], t["confidence"]
        auto, cross = t["autocorrelation"], t.get("cross_correlation") or {}

        def verdict(v):
            return "&ndash;" if v is None else ("yes" if v else ("no", "best"))

        rows.append(head + [_fmt(t["n"]), _fmt(c.get("fit")),
                            f"{auto['n_outside']} / {len(auto['lag'])}", _fmt(auto["ljung_box"]["p_value"]),
                            verdict(auto["white"]),
                            f"{cross['n_outside']} / {len(cross['lag'])}" if cross else "&ndash;",
                            _fmt((cross.get("portmanteau") or {}).get("p_value")), verdict(cross.get("independent"))])
    parts.append(_table(["record", "role", "n", "one-step fit [%]", "autocorr. lags outside", "Ljung-Box p",
                         "white", "cross-corr. lags outside", "portmanteau p", "independent of u"], rows,
                        left_cols=2))
    level = f"{100 * conf:g} %" if conf is not None else "99 %"
    parts.append(
        "<p class='note'>One-step-ahead residuals e = y &minus; &mu; (eqs. 8-9 from the measured lags) of the "
        "verify and validate records: their autocorrelation at lags 1.." + _fmt(lags) + " and their "
        "cross-correlation with the input u at lags &minus;" + _fmt(lags) + ".." + _fmt(lags) + " (u leads e for "
        "positive lags), both normalised, means removed, with the " + level + " limits &plusmn;z/&radic;N, which "
        "hold for a white residual independent of the input (about 1 % of lags outside then). White: Ljung-Box "
        "p &ge; 0.01; independent of u: the portmanteau N &Sigma; r<sub>ue</sub><sup>2</sup> (2L+1 degrees of "
        "freedom) p &ge; 0.01 (no: in bold). Residuals that still correlate with the input mean dynamics the "
        "model has not learnt, however good its fit; coloured residuals that do not are model error or "
        "coloured measurement noise. On long records the limits are narrow: judge the size of the "
        "correlations in the figures too.</p>")
    for e in tested:
        fn = e.get("residual_figure")
        if fn:
            parts.append(f"<figure>{_img(fn, 'residual tests of ' + e['name'], embedded)}<figcaption>"
                         f"<b>{esc(e['name'])}</b> ({esc(str(e.get('role', '')))}): one-step residuals' (a) "
                         f"autocorrelation and (b) cross-correlation with the input, {level} limits dashed, lags "
                         f"outside them in red.</figcaption></figure>")
    return parts


def figures_missing(summary: dict | None = None) -> str | None:
    """Why this process draws no report figures and how to get them (None: it draws them). ``summary``'s
    ``config`` (the trained config's path) names the command that trains again: a shipped config by its name."""
    if record_figure is not None:
        return None
    from gpnarx.configs import CONFIG_DIR

    cfg = (summary or {}).get("config")
    again = ""
    if cfg:
        p = Path(str(cfg))
        ref = p.stem if p.parent.resolve() == CONFIG_DIR.resolve() else str(p)
        again = f" (gpnarx train {ref} --registry REGISTRY writes a new version with them)"
    return FIGURES_MISSING + again


def render_record(rec: dict, physics: dict | None) -> tuple[dict, bytes | None]:
    """One record's computed metrics and its figure as PNG bytes (None where matplotlib is missing): the
    report's per-record work as one task (a Dask worker runs it on the record sent to it; the client writes
    the files)."""
    computed = record_metrics(rec, physics)
    merged = {**to_report_json(rec.get("metrics") or {}), **computed}
    if record_figure is None:
        return computed, None
    with FIGURE_LOCK, tempfile.TemporaryDirectory() as tmp:
        png = record_figure(dict(rec, metrics=merged), physics, Path(tmp) / "record.png")
        return computed, png.read_bytes()


def write_report(out_dir: Path, title: str, summary: dict, records: list[dict], physics: dict | None = None,
                 lag_surface: dict | None = None, baselines: dict | None = None, paper: dict | None = None,
                 runner=None) -> dict:
    """Write report.json, one PNG per record, lag_surface.png (if given) and report.html to ``out_dir``;
    without matplotlib no PNG, report.json's ``figures_missing`` and the page say why (``figures_missing``).

    ``lag_surface``: {"surface" (or "cells"): [{"ny", "nu", "fit"}...], "chosen": (ny, nu) or {"ny", "nu"},
    "paper": (ny, nu, fit) or {"ny", "nu", "fit"}} (training.lags.lag_surface output works as is)
    (a plain list of rows is accepted; ``paper["lags"]`` supplies the paper's point when absent).
    ``baselines``: {record_name: {model_name: {"fit": .., "rmse": ..}}}.
    ``paper``: {"lags": {"ny", "nu", "fit"}, "records": {record_name: {"fit": ..}}}.

    ``runner`` (a ``training.distributed.TaskRunner`` on a Dask cluster): each record's metrics and
    figure are computed as a task (:func:`render_record`); the files are written here all the same.

    A record may carry ``residual_tests`` (``training.report_residuals.attach_residual_tests``: the training
    pipeline's verify and validate records): written to its report.json entry, a table on the page and, with
    matplotlib, a figure ``residuals_<record>.png`` (``residual_figure``).

    Returns {"json": Path, "html": Path, "lag_surface": Path | None, "records": {name: Path}} and, where residual
    figures were drawn, "residuals": {name: Path}.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict = {"records": {}, "lag_surface": None}

    missing = figures_missing(summary)
    rendered = None
    if runner is not None and runner.distributed:
        rendered = runner.run(render_record, [(runner.send(rec), physics) for rec in records])
    rec_entries, fig_names, used = [], {}, set()
    for i, rec in enumerate(records):
        name = str(rec.get("name", f"record{i}"))
        computed = record_metrics(rec, physics) if rendered is None else rendered[i][0]
        given = to_report_json(rec.get("metrics") or {})
        merged = {**given, **computed}
        extra = {k: v for k, v in given.items() if k not in computed}
        fn = f"record_{slug(name)}.png"
        k = 2
        while fn in used:
            fn = f"record_{slug(name)}_{k}.png"
            k += 1
        used.add(fn)
        if rendered is None:
            if missing is None:
                paths["records"][name] = record_figure(dict(rec, metrics=merged), physics, out_dir / fn)
                fig_names[name] = fn
        elif rendered[i][1] is not None:
            (out_dir / fn).write_bytes(rendered[i][1])
            paths["records"][name] = out_dir / fn
            fig_names[name] = fn
        rec_entries.append({"name": name, "role": rec.get("role"), "fs": finite_or_none(rec.get("fs")),
                            "units": dict(rec.get("units") or {}), "figure": fig_names.get(name), "metrics": merged,
                            "extra_metrics": extra, "band_label": rec.get("band_label", "99% band")})
        if rec.get("residual_tests") is not None:  # verify/validate records (training.report_residuals)
            rec_entries[-1]["residual_tests"] = to_report_json(rec["residual_tests"])
            if missing is None and not rec["residual_tests"].get("error"):
                rfn = "residuals_" + fn[len("record_"):]
                with FIGURE_LOCK:
                    residual_figure(rec["residual_tests"], name, out_dir / rfn)
                paths.setdefault("residuals", {})[name] = out_dir / rfn
                rec_entries[-1]["residual_figure"] = rfn

    lag = _norm_lag_surface(lag_surface, paper)
    lag_png = None
    if lag is not None and lag[0] and missing is None:
        paths["lag_surface"] = lag_surface_figure(lag[0], lag[1], lag[2], out_dir / "lag_surface.png")
        lag_png = "lag_surface.png"

    # baselines side by side with GP-NARX
    baselines_json = to_report_json(baselines or {})
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
        "summary": to_report_json(summary or {}),
        "physics": to_report_json(physics) if physics else None,
        "records": [{k: v for k, v in e.items() if k not in ("extra_metrics", "band_label")} for e in rec_entries],
        "lag_surface": None if lag is None else {
            "table": lag[0], "chosen": list(lag[1]) if lag[1] else None,
            "paper": to_report_json(list(lag[2])) if lag[2] else None,
            "best": to_report_json(_best_cell(lag[0])),
            "edge": _lag_edge(lag[0]),
            "figure": lag_png},
        "baselines": baselines_json,
        "comparison": None if baselines_tab is None else to_report_json(
            {r: {**f, "best": max((m for m in f if finite_or_none(f[m]) is not None), key=lambda m: f[m], default=None)}
             for r, f in baselines_tab["rows"].items()}),
        "paper": to_report_json(paper) if paper else None,
        "figures_missing": missing,
    }
    report = to_report_json(report)
    jpath = out_dir / "report.json"
    jpath.write_text(json.dumps(report, indent=2, allow_nan=False))
    paths["json"] = jpath

    # figures embedded as data URIs: the page is self-contained (the PNG files stay for other uses)
    residual_pngs = [e["residual_figure"] for e in rec_entries if e.get("residual_figure")]
    embedded = {fn: _png_data_uri(out_dir / fn)
                for fn in [*fig_names.values(), *residual_pngs, *([lag_png] if lag_png else [])]}
    hpath = out_dir / "report.html"
    hpath.write_text(_html(title, report["summary"], rec_entries, lag, baselines_tab, paper, fig_names, lag_png,
                           embedded, missing), encoding="utf-8")
    paths["html"] = hpath
    return paths
