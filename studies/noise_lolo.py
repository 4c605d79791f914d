"""Leave one noise level out: the real-rig model trained without one broadband noise run, scored on it.

A plant sends noise levels the model never saw. For each noise run of the data folder (``real_table``'s
class ``noise``), the shipped config is refitted with that run taken out of every role and the config's
noise windows moved onto the other runs: each ``train`` window of a noise run becomes the same window of
every other noise run (same meta and row weight), each ``lags`` window likewise, and a ``validate`` noise
run is dropped. The refitted model (``training.pipeline.fit``: ML-II, the noise and band calibrations,
the config's own ``[model]``) predicts the held-out run whole, from rest, by the linearised method and,
unless skipped, by Monte Carlo; next to it the class ARX of ``real_table`` (ny = nu = ``CLASS_ARX_LAGS``,
least squares on the other noise runs, whole), which by construction never saw that level either.

Units: u [V], y [m/s], half-widths [m/s].
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from gpnarx.storage.record_files import read_record
from gpnarx.training.baselines import LinearARX
from studies import real_table as rt
from studies.real_table import CLASS_ARX_LAGS, TARGETS, Z99, find_records, record_class

NOISE = "noise"


def noise_runs(data_dir) -> dict[str, tuple[Path, object]]:
    """{folder name: (folder, its record)} of the data folder's broadband noise runs (``real_table.record_class``)."""
    out = {}
    for f in find_records(data_dir):
        rec = read_record(f)
        if record_class(f, rec) == NOISE:
            out[f.name] = (f, rec)
    return out


def fold_config(cfg, held: Path, others: list[Path]):
    """``cfg`` with the noise run ``held`` out of every role: the config's noise-run specs (those whose path is
    a noise run) are replaced by the same spec on each of ``others`` (train and lags), validate-only ones
    dropped. Raises ValueError when the config trains on no noise run (nothing to move)."""
    noise_paths = {str(Path(p).resolve()) for p in [held, *others]}
    keep, moved = [], []
    for spec in cfg.records:
        if spec.path is None or str(Path(spec.path).resolve()) not in noise_paths:
            keep.append(spec)
            continue
        roles = [r for r in spec.roles if r in ("train", "lags")]
        if not roles:
            continue
        for other in others:
            moved.append(dataclasses.replace(spec, name=f"{spec.name}@{other.name}", roles=list(roles),
                                             path=other, meta=dict(spec.meta)))
    if not any("train" in s.roles for s in moved):
        raise ValueError(f"{cfg.path}: no train window of a noise run to move off {held.name}")
    # one spec per (window, run): a run named by several specs of the config keeps them all
    return dataclasses.replace(cfg, records=keep + moved)


def _scores(rec, run, env, arx_rmse: float | None) -> dict:
    """``real_table``'s scores of a whole-record run, with the sharpness against the class ARX's RMS error."""
    g = rt._scores(rec.y, run, rec.u, env)
    g["sharpness"] = g["half_width"] / (Z99 * arx_rmse) if g["half_width"] is not None and arx_rmse else None
    return g


def lolo_table(cfg, data_dir, *, mc_paths: int = 1024, seed: int = 0, max_seconds: float | None = None,
               fit=None, log=None) -> dict:
    """For each noise run: the fold model (``fold_config``, fitted by ``fit(cfg_fold)``, default
    ``training.pipeline.fit`` on its own train and lags records) scored on the held-out run whole and from
    rest (``max_seconds``: its first seconds, quick mode), linearised and with ``mc_paths`` Monte Carlo paths
    (0: linearised only), next to the class ARX fitted on the other noise runs.

    Returns ``{"runs": {name: row}, "mc_paths", "targets", "checks", "seconds"}``.
    """
    log = log or (lambda m: None)
    if fit is None:
        from gpnarx.training.pipeline import fit as pipeline_fit

        def fit(c):
            return pipeline_fit(c, c.records_for("train"), c.records_for)
    t0 = time.perf_counter()
    found = noise_runs(data_dir)
    runs = {name: folder for name, (folder, _) in found.items()}
    recs = {name: rec for name, (_, rec) in found.items()}
    rows = {}
    for name, folder in runs.items():
        others = [f for n, f in runs.items() if n != name]
        if not others:
            continue
        t1 = time.perf_counter()
        model = fit(fold_config(cfg, folder, others))
        rec = recs[name]
        if max_seconds:
            rec = rec.window(0.0, min(max_seconds, rec.n / rec.fs))
        arx = rt._arx_scores(LinearARX(*CLASS_ARX_LAGS).fit([recs[f.name] for f in others]), rec)
        env = getattr(model, "envelope_", None)
        with np.errstate(all="ignore"):
            row = {"trained_on": [f.name for f in others], "input_rms": float(np.std(rec.u)),
                   "measured_std": float(np.std(rec.y)), "arx_class": {"fit": arx["fit"], "rmse": arx["rmse"]},
                   "whole_linear": _scores(rec, model.simulate(rec.u, method="linear"), env, arx["rmse"])}
            if mc_paths:
                row["whole_mc"] = _scores(rec, model.simulate(rec.u, n_paths=int(mc_paths), seed=seed), env,
                                          arx["rmse"])
        row["fold_seconds"] = time.perf_counter() - t1
        rows[name] = row
        g = row["whole_linear"]
        log(f"  leave {name} out (trained on {', '.join(row['trained_on'])}): fit {g['fit']:.1f} % "
            f"(class ARX {rt._fmt(arx['fit'])} %), coverage {g['coverage']:.1f} %, sharpness {g['sharpness']:.2f}")
    table = {"runs": rows, "mc_paths": int(mc_paths), "targets": dict(TARGETS), "max_seconds": max_seconds,
             "seconds": time.perf_counter() - t0}
    table["checks"] = lolo_checks(table)
    return table


def lolo_checks(table: dict) -> dict:
    """Per method: the held-out runs whose fit is below the class ARX's, the lowest coverage, the largest
    sharpness, and ``met`` (fit at least the ARX's, coverage at least 90 %, sharpness at most 1.5 on every run)."""
    out = {}
    for key in ("whole_linear", "whole_mc"):
        rows = {n: r for n, r in table["runs"].items() if key in r}
        if not rows:
            continue
        below = [n for n, r in rows.items() if r[key]["fit"] is None
                 or (r["arx_class"]["fit"] is not None and r[key]["fit"] < r["arx_class"]["fit"])]
        cov = min(r[key]["coverage"] for r in rows.values())
        sharp = [r[key]["sharpness"] for r in rows.values() if r[key]["sharpness"] is not None]
        out[key] = {"below_arx": below, "min_coverage": cov, "max_sharpness": max(sharp) if sharp else None,
                    "met": (not below and cov >= TARGETS["min_coverage"]
                            and (not sharp or max(sharp) <= TARGETS["max_noise_sharpness"]))}
    return out


def markdown(table: dict) -> str:
    """The leave-one-level-out table as Markdown (a section of docs/results-bert-real.md)."""
    mc = bool(table.get("mc_paths"))
    fmt = lambda v, nd=1: "n/a" if v is None else f"{v:.{nd}f}"  # noqa: E731
    lines = ["| held-out noise run | input RMS [V] | trained on | fit % (lin.) | fit % (MC) | class ARX fit % | "
             "coverage % (lin.) | coverage % (MC) | half-width / std (lin.) | sharpness (lin.) | sharpness (MC) |",
             "|" + "---|" * 11]
    for name, r in sorted(table["runs"].items(), key=lambda kv: kv[1]["input_rms"]):
        lin, g = r["whole_linear"], r.get("whole_mc", {})
        lines.append(f"| {name} | {r['input_rms']:.5f} | {', '.join(r['trained_on'])} | {fmt(lin['fit'])} | "
                     f"{fmt(g.get('fit')) if mc else 'n/a'} | {fmt(r['arx_class']['fit'])} | {lin['coverage']:.1f} | "
                     f"{fmt(g.get('coverage')) if mc else 'n/a'} | {fmt(lin['half_width_over_std'], 2)} | "
                     f"{fmt(lin['sharpness'], 2)} | {fmt(g.get('sharpness'), 2) if mc else 'n/a'} |")
    lines.append("")
    for key, m in table.get("checks", {}).items():
        label = "linearised" if key == "whole_linear" else f"{table['mc_paths']}-path Monte Carlo"
        lines.append(f"- {label}: held-out runs below the class ARX's fit: {', '.join(m['below_arx']) or 'none'}; "
                     f"lowest coverage {m['min_coverage']:.1f} % (target 90 %); largest sharpness "
                     f"{fmt(m['max_sharpness'], 2)} (target 1.5); targets {'met' if m['met'] else 'NOT met'}.")
    return "\n".join(lines) + "\n"
