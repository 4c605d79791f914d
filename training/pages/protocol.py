"""The protocol results pages (docs/results-bouc-wen.md, docs/results-bert-standin.md and the paper's
protocol on the real rig, docs/results-bert-real-paper.md),
rendered from one ``gpnarx reproduce`` run's own JSON (``summary.json`` and ``lag_surface.json``) and
nothing else: every figure on the page is a value of that run, so the page cannot drift from it.
``gpnarx reproduce SYSTEM --docs FILE`` writes it at the end of the run, ``gpnarx reproduce SYSTEM
--out RUN --from-run --docs FILE`` re-renders it from a finished run folder.

The prose around the tables holds no figures; studies that are not part of the protocol run (the
Bouc-Wen 10 N investigation, the stand-in's calibration and scatter) live on their own pages.
"""
from __future__ import annotations

from gpnarx.training.pages.markdown import hz, lines, pct, sig, table
from gpnarx.training.report_metrics import USES

# the order records are listed in: what trained the model, what chose the lags, then held-out records
USE_ORDER = ("training", "lag-selection", "calibration", "held-out")
USE_LABEL = {"training": "training", "lag-selection": "lag selection", "calibration": "novelty calibration",
             "held-out": "held out"}


def _ordered(records: dict) -> list[tuple[str, dict]]:
    rank = {u: i for i, u in enumerate(USE_ORDER)}
    return sorted(records.items(), key=lambda kv: rank.get(kv[1].get("use"), len(rank)))


def _baseline_names(baselines: dict | None) -> list[str]:
    names = []
    for per in (baselines or {}).values():
        for k in per:
            if k not in names:
                names.append(k)
    return names


def _baseline_fit(baselines: dict | None, rec: str, model: str, key: str):
    b = ((baselines or {}).get(rec) or {}).get(model) or {}
    return b.get(key)


def _run_line(summary: dict) -> str:
    ch = summary["chosen_lags"]
    return (f"Run: chosen lags ny={ch['ny']}, nu={ch['nu']} (lag-surface fit {pct(ch['fit'])} %); "
            f"{summary['mc_paths']} Monte Carlo paths, 99 % bands; wall time "
            f"{summary.get('wall_seconds', float('nan')):.0f} s"
            + (" (quick mode: tiny grid, short records, few paths; not the protocol's figures)"
               if summary.get("quick") else "") + ".\n\n")


def _columns_note(clean: bool) -> str:
    uses = "; ".join(f"**{USE_LABEL[u]}**: {USES[u]}" for u in USE_ORDER)
    s = (f"Use: {uses}. Role: the record's scoring role in the config (`lags`, `verify`, `validate`, ...). "
         "Fit: eq. (14) of the free-run Monte Carlo mean against the measured (noisy) output. ")
    if clean:
        s += ("Fit clean: the same mean against the simulator's noise-free output. **Coverage**: % of measured "
              "samples inside the 99 % *predictive* band (the band of y, noise variance sigma_y^2 included). "
              "**Coverage latent**: % of noise-free samples inside the 99 % *latent* band (the band of the "
              "noise-free output f, the same propagation without the noise term). Each band is scored against "
              "the output it is a band of; the predictive band scored against the noise-free output would "
              "over-cover (older reports' `coverage_clean`). ")
    else:
        s += "Coverage: % of measured samples inside the 99 % predictive band (noise included). "
    s += "Band width: mean width of the predictive band. Baselines are fitted on the same training records."
    return s + "\n\n"


def records_table(summary: dict, clean: bool, baseline_key: str, oracle: dict | None = None) -> str:
    """The per-record table, grouped by use; baselines scored by ``baseline_key`` ('fit' or 'fit_clean')."""
    unit = summary.get("units", {}).get("y", "")
    bnames = _baseline_names(summary.get("baselines"))
    bl = "fit clean" if baseline_key == "fit_clean" else "fit"
    head = ["record", "use", "role", "fit %"] + (["fit clean %"] if clean else []) + ["coverage %"] + \
        (["coverage latent %"] if clean else []) + [f"band width{f' [{unit}]' if unit else ''}"] + \
        (["nominal stand-in (oracle) fit clean %"] if oracle else []) + [f"{b} {bl} %" for b in bnames] + \
        ["PSD peak measured / predicted [Hz]"]
    rows = []
    for name, r in _ordered(summary["records"]):
        peaks = (r.get("psd_peaks_measured") or [None])[0], (r.get("psd_peaks_predicted") or [None])[0]
        cells = [name, USE_LABEL.get(r.get("use"), str(r.get("use"))), str(r.get("role")), pct(r.get("fit"))]
        if clean:
            cells.append(pct(r.get("fit_clean")))
        cells.append(pct(r.get("coverage")))
        if clean:
            cells.append(pct(r.get("coverage_latent")))
        cells.append(sig(r.get("band_width")))
        if oracle:
            cells.append(pct((oracle.get(name) or {}).get("fit_clean")))
        for b in bnames:
            v = _baseline_fit(summary.get("baselines"), name, b, baseline_key)
            cells.append("unstable" if v is not None and v < -1e4 else pct(v))
        cells.append(f"{hz(peaks[0])} / {hz(peaks[1])}")
        rows.append(cells)
    return "\n".join(table(head, rows)) + "\n\n"


def lags_table(summary: dict, surface: dict | None) -> str:
    ch, paper = summary["chosen_lags"], summary["paper_lags"]
    s = ("| | this run | paper |\n|---|---|---|\n"
         f"| chosen lags | ny={ch['ny']}, nu={ch['nu']} | ny={paper['ny']}, nu={paper['nu']} |\n"
         f"| lag-surface fit of the chosen cell % | {pct(ch['fit'])} | {pct(paper['fit'])} |\n")
    if surface and surface.get("best"):
        b = surface["best"]
        s += f"| best cell | ny={b['ny']}, nu={b['nu']}: {pct(b['fit'])} | |\n"
    s += "\n"
    if summary.get("lag_grid_edge"):
        s += (f"The best cell sits on the grid's largest {' and '.join(summary['lag_grid_edge'])} "
              "(`lag_grid_edge` in the summary).\n\n")
    if surface and surface.get("cells"):
        names = sorted({k for c in surface["cells"] for k in (c.get("fits") or {})})
        criterion = ("the smallest ny + nu within "
                     f"{surface.get('tolerance', 0.5)} points of the best" if surface.get("criterion") != "worst"
                     else "the highest worst-record fit")
        fits = {(c["ny"], c["nu"]): c.get("fit") for c in surface["cells"]}
        s += (f"Lag surface: free-run fit % of a model trained at each (ny, nu) on the `train` records, scored on "
              f"the `lags` record(s) ({', '.join(names)}); chosen by {criterion}.\n\n"
              + lines(table(["ny \\ nu"] + [str(v) for v in surface["nu"]],
                            [[str(ny)] + [pct(fits.get((ny, nu))) for nu in surface["nu"]] for ny in surface["ny"]]))
              + "\n")
    return s


def loops_table(summary: dict) -> str:
    rows = [(n, r) for n, r in _ordered(summary["records"]) if r.get("loop_area_predicted") is not None]
    if not rows:
        return ""
    return ("Loop areas (restoring force R = u - m y'' against y, J): the noise-free, measured and predicted loops "
            "of each record.\n\n"
            + lines(table(["record", "use", "noise-free", "measured", "predicted"],
                          [[n, USE_LABEL.get(r.get("use"), ""), sig(r.get("loop_area_clean"), 4),
                            sig(r.get("loop_area_measured"), 4), sig(r.get("loop_area_predicted"), 4)]
                           for n, r in rows])) + "\n")


def config_lags(system: str, summary: dict) -> tuple[dict, str]:
    """The lags the system's config sets: the run's own record of them (``config_lags``, written by gpnarx
    reproduce) or, for a run that predates it, the shipped config's as it is now; with the words for which."""
    if summary.get("config_lags"):
        return summary["config_lags"], "set"
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config

    model = load_config(shipped_config(system)).model
    return {"ny": model.get("ny"), "nu": model.get("nu")}, "sets (as it is now; the run predates its record of them)"


def model_line(system: str, summary: dict) -> str:
    """Which model the page's figures come from, and whether the shipped config trains the same lags."""
    ch = summary["chosen_lags"]
    lags, when = config_lags(system, summary)
    s = (f"Model of these figures: ny={ch['ny']}, nu={ch['nu']}, the lags this run chose on its lag surface, with "
         f"every other setting of `configs/{system}.toml`. ")
    if (lags.get("ny"), lags.get("nu")) == (ch["ny"], ch["nu"]):
        return s + f"The shipped `{system}` config {when.split(' ')[0]} the same lags.\n\n"
    return s + (f"The shipped `{system}` config {when} ny={lags.get('ny')}, nu={lags.get('nu')}: the model "
                f"`gpnarx train {system}` and the default registry build is not this page's model, and its figures "
                "differ.\n\n")


def _header(title: str, system: str, summary: dict) -> str:
    return (f"# {title}\n\n"
            f"Rendered from one run's own figures (`summary.json`, `lag_surface.json`), kept in `docs/runs/{system}/`; "
            "do not edit by hand (a test re-renders this page from that JSON). To regenerate: "
            f"`gpnarx reproduce {system} --out RUN --docs docs/results-{system}.md`, then copy `RUN/summary.json` and "
            f"`RUN/lag_surface.json` to `docs/runs/{system}/`; `gpnarx reproduce {system} --out docs/runs/{system} "
            f"--from-run --docs docs/results-{system}.md` re-renders it without computing. The run's bundle report "
            "(`report.html`) holds the same records with figures.\n\n" + _run_line(summary)
            + model_line(system, summary))


def _sections(summary: dict, surface: dict | None, *, lags: str = "Lags", records: str = "Records",
              clean: bool = True, key: str = "fit", oracle: dict | None = None, loops: bool = True) -> str:
    """The lags and the per-record table (and the loop areas) every protocol page holds."""
    return (f"## {lags}\n\n" + lags_table(summary, surface)
            + f"## {records}\n\n" + _columns_note(clean) + records_table(summary, clean, key, oracle=oracle)
            + (loops_table(summary) if loops else ""))


def bouc_wen_page(summary: dict, surface: dict | None = None) -> str:
    page = _header("Results: Bouc-Wen benchmark (section 3)", "bouc-wen", summary)
    page += ("Protocol (`configs/bouc-wen.toml`): train on the 10 N and 80 N sweeps (5-150 Hz, 53 Hz/s) with output "
             "noise of 10 % of the energy of the 10 N response; lag surface judged on the 50 N sweep; the "
             "verification rows of the 10 and 80 N sweeps are therefore the training records, and the 50 N row "
             "is the lag-selection record; only the 35.59 Hz sines and the multisines at 10/50/80 N are held out. "
             "Baselines are scored against the noise-free output. The investigation of the 10 N sweep's miss "
             "and of remedies is in [study-bouc-wen-10n.md](study-bouc-wen-10n.md).\n\n")
    return page + _sections(summary, surface, key="fit_clean")


def standin_page(summary: dict, surface: dict | None = None) -> str:
    page = _header("Results: BERT stand-in (section 4 protocol)", "bert-standin", summary)
    page += ("**These are stand-in numbers, never the rig's.** The real records are in "
             "[results-bert-real.md](results-bert-real.md); the stand-in itself (its calibration against the real "
             "records, realization scatter, torque law) is described in [standin.md](standin.md).\n\n"
             "Protocol (`configs/bert-standin.toml`): train on 0.05 V and 0.20 V sweeps (0-40 Hz, 5 Hz/s, 16384 "
             "samples at 1024 Hz) of several realizations; lag surface judged on a 0.10 V sweep realization; "
             "held out: a 0.15 V sweep, an 18 Hz sine at 0.15 V and 0-110 Hz noise at 0.30 V, each a new "
             "realization. The paper uses 4096 Monte Carlo paths. \"Nominal stand-in (oracle)\": the stand-in's "
             "own nominal equations predicting the realization, what realization scatter alone costs.\n\n")
    page += _sections(summary, surface, oracle=summary.get("oracle"), loops=False)
    mon = summary.get("monitor")
    if mon:
        page += ("## The bolt-loosening monitor\n\n`configs/bert-standin-monitor.toml`, trained by the same run: "
                 "its probe is a steady 0.15 V sine at 9 Hz; its healthy records set the novelty threshold "
                 "(use: novelty calibration), its damaged and validate records are held out.\n\n")
        nv = mon.get("novelty") or {}
        if nv:
            page += (f"Threshold {sig(nv.get('threshold'), 4)} at a {pct(100 * nv['false_alarm_rate'])} % "
                     f"false-alarm rate from {nv.get('n_healthy')} healthy records.\n\n")
        page += lines(table(
            ["record", "use", "role", "fit %", "fit clean %", "coverage %", "coverage latent %", "novelty score",
             "verdict"],
            [[name, USE_LABEL.get(r.get("use"), ""), str(r.get("role")), pct(r.get("fit")), pct(r.get("fit_clean")),
              pct(r.get("coverage")), pct(r.get("coverage_latent")), sig(r.get("novelty_score"), 4),
              str(r.get("verdict", ""))] for name, r in _ordered(mon["records"])])) + "\n"
    nov = summary.get("novelty")
    if nov:
        classes = list(nov["scores"])
        page += ("## Bolt loosening (novelty study)\n\n"
                 f"Each record: {nov['record_seconds']:.0f} s of the probe, a new seeded realization, "
                 f"{'linearised' if not nov.get('mc_paths') else str(nov['mc_paths']) + '-path Monte Carlo'} "
                 f"free run from its first ny measured outputs, score method `{nov.get('method')}`. Thresholds: the "
                 f"quantile of a log-normal fit to {len(nov['calibration_scores'])} healthy 5 N m calibration "
                 f"realizations; {nov['n_per_class']} records per class below, none used for calibration. "
                 f"Direction: {nov.get('direction')}. ROC curve: `novelty_roc.png` in the run folder.\n\n")
        n = nov["n_per_class"]
        page += lines(table(
            ["false-alarm rate", "threshold"] + [f"{c} flagged" for c in classes],
            [[f"{pct(100 * float(far))} %", sig(thr, 4)]
             + [f"{round(nov['rates'][far][c] * n)} / {n} ({pct(100 * nov['rates'][far][c])} %)" for c in classes]
             for far, thr in nov["thresholds"].items()]))
        page += ("\nScores (min-max): " + "; ".join(
            f"{c} {sig(min(v), 4)}-{sig(max(v), 4)}" for c, v in nov["scores"].items())
            + f"; calibration {sig(min(nov['calibration_scores']), 4)}-{sig(max(nov['calibration_scores']), 4)}.\n")
    return page


def real_paper_page(summary: dict, surface: dict | None = None) -> str:
    page = _header("Results: the paper's section 4 protocol on the real BERT rig (UNESP, 5 N m)", "bert-real-paper",
                   summary)
    page += ("Real records, read in place from `$GPNARX_BERT_DATA` (default `../shared/data/bert-t5nm`). Protocol "
             "(`configs/bert-real-paper.toml`), as far as the shared records allow (one realization per level, "
             "where the paper had 50): train on the 0.05 V and 0.20 V swept sines (0-40 Hz at 5 Hz/s, 16384 samples "
             "at 1024 Hz, from rest) with the ML-II rows drawn around the resonance (section 4.2); lag surface "
             "judged on the 0.10 V sweep; verification on the three sweeps (their rows below are the training "
             "records and the lag-selection record, Figs. 15-17: time response with the band, PSD and "
             "restoring-force loops are in the run's `report.html`); validation on records the protocol never "
             "saw: the 9 Hz and 19 Hz sines at 0.15 V (their first 16 s, from rest) and the 0.25 V noise run. "
             "The band is the method's own, eqs. (8)-(9) propagated by Monte Carlo, with no calibration. The "
             "model shipped for every excitation class is `bert-real` ([results-bert-real.md]"
             "(results-bert-real.md)).\n\n")
    page += _sections(summary, surface, lags="Lags (the 0.10 V sweep)", records="Verification and validation",
                      clean=False)
    rec = summary.get("receptance") or {}
    if rec.get("runs"):
        page += ("## Receptance of the sweeps (Fig. 12(a))\n\nFrom each sweep's LMS FRF export (velocity per volt, "
                 "divided by 2 pi f: displacement per volt). The peak moving down and flattening as the drive "
                 "grows is the joint's softening and added damping. Figure: `docs/runs/bert-real-paper/"
                 "receptance.png`.\n\n![receptance](runs/bert-real-paper/receptance.png)\n\n"
                 + lines(table(["sweep", "RMS drive [V]", "receptance peak [Hz]", "peak [m/V]"],
                               [[r["name"], sig(r["u_rms"], 3), f"{r['peak_freq']:.4g}", sig(r["peak"], 4)]
                                for r in rec["runs"]])) + "\n")
    return page


PAGES = {"bouc-wen": bouc_wen_page, "bert-standin": standin_page, "bert-real-paper": real_paper_page}

__all__ = ["PAGES", "bouc_wen_page", "lags_table", "real_paper_page", "records_table", "standin_page"]
