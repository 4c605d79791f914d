"""The real-rig results table: every real record of a data folder, whole and windowed, GP-NARX next to
linear ARX baselines fitted on the same training records.

For each record found under the data folder (``Sine/*`` and ``Rand/*`` LMS exports; records a user
adds there are picked up too) and its role in the dataset config (``train`` when any training
window comes from it, ``lags`` when it chose the lags, ``validate`` when it is held out, ``unseen``
when the config does not name it):

* whole record, free run from rest (start-up transient, steady state and free decay): the
  linearised run and, unless skipped, a Monte Carlo run (``mc_paths`` paths): fit % (eq. 14), the
  peak ratio max|mean| / max|y| (divergence shows as a ratio far above 1), coverage of the 99 %
  predictive band (noise included) against the measured output, mean band width, diverged paths
  and the out-of-range flags (``model.envelope``);
* a steady window (``WINDOW`` s: 30-32 s of a sine, 10-12 s of a noise run) free-run from its first
  ny measured outputs: the same figures;
* two linear ARX baselines fitted by least squares on the same training records: ny=8, nu=4 and
  the GP-NARX's own lags, simulated the same way;
* between the recorded frequencies, the model's steady sine response against the rig's own FRF
  (``training.frf_check``), when the noise run's LMS ``FRF.mat`` is in the data folder.

Units: u [V], y [m/s], times [s]. The numbers come from the run that writes them.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gpnarx.model.envelope import assess
from gpnarx.model.metrics import band_width, coverage, fit_percent
from gpnarx.model.records import Record
from gpnarx.training.baselines import LinearARX
from gpnarx.training.frf_check import frf_check
from gpnarx.training.records import read_record

SINE_WINDOW = (30.0, 32.0)  # s: steady state of a 64 s sine (the drive runs 0-51 s)
NOISE_WINDOW = (10.0, 12.0)  # s: inside a 16 s noise run
ARX_LAGS = (8, 4)  # the small ARX a user would fit first (next to one at the GP-NARX's lags)


def find_records(data_dir) -> list[Path]:
    """LMS record folders (``Time.mat`` + ``TimeShaker.mat``) under ``data_dir``, sines first."""
    data_dir = Path(data_dir)
    found = [p.parent for p in data_dir.rglob("TimeShaker.mat") if (p.parent / "Time.mat").is_file()]
    return sorted(found, key=lambda p: (p.parent.name != "Sine", p.parent.name, p.name))


def record_roles(cfg) -> dict:
    """{resolved record folder: sorted roles} from a dataset config's record specs."""
    roles: dict[str, set] = {}
    for spec in cfg.records:
        if spec.path is None:
            continue
        roles.setdefault(str(Path(spec.path).resolve()), set()).update(spec.roles)
    return {k: sorted(v) for k, v in roles.items()}


def role_of(roles: list) -> str:
    for r in ("train", "lags", "validate"):
        if r in roles:
            return r
    return "unseen" if not roles else roles[0]


def _window(rec: Record, span) -> Record:
    i, j = int(round(span[0] * rec.fs)), int(round(span[1] * rec.fs))
    return Record(rec.u[i:j], rec.y[i:j], rec.fs, dict(rec.units), rec.name, dict(rec.meta))


def _scores(y, run, u, env) -> dict:
    mean = run.mean
    with np.errstate(all="ignore"):
        f = fit_percent(y, mean)
        peak = float(np.max(np.abs(mean)) / max(float(np.max(np.abs(y))), 1e-300))
    out = {"fit": float(f) if np.isfinite(f) else None, "peak_ratio": peak if np.isfinite(peak) else None,
           "coverage": coverage(y, run.lower, run.upper), "band_width": band_width(run.lower, run.upper),
           "seconds": float(run.seconds)}
    out.update(assess(env, run, u, y))
    return out


def _arx_scores(arx: LinearARX, rec: Record, y0=None) -> dict:
    with np.errstate(all="ignore"):
        yh = arx.simulate(rec.u, y0=y0)
        f = fit_percent(rec.y, yh)
        peak = float(np.max(np.abs(yh)) / max(float(np.max(np.abs(rec.y))), 1e-300))
    return {"fit": float(f) if np.isfinite(f) else None, "peak_ratio": peak if np.isfinite(peak) else None}


def _row(model, arx: dict, folder: Path, role: str, mc_paths: int, seed: int, max_seconds) -> dict:
    """One record's row (see the module docstring); runs in a worker process when jobs > 1."""
    env = getattr(model, "envelope_", None)
    rec = read_record(folder)
    whole = rec if not max_seconds else _window(rec, (0.0, max_seconds))
    span = NOISE_WINDOW if folder.parent.name.lower().startswith("rand") else SINE_WINDOW
    win = _window(rec, span)
    y0 = win.y[: model.ny]
    row = {"role": role, "seconds_long": whole.n / whole.fs, "window": list(span),
           "measured_peak": float(np.max(np.abs(whole.y))), "input_peak": float(np.max(np.abs(whole.u)))}
    with np.errstate(all="ignore"):
        row["whole_linear"] = _scores(whole.y, model.simulate(whole.u, method="linear"), whole.u, env)
        row["window_linear"] = _scores(win.y, model.simulate(win.u, method="linear", y0=y0), win.u, env)
        if mc_paths:
            row["whole_mc"] = _scores(whole.y, model.simulate(whole.u, n_paths=mc_paths, seed=seed), whole.u, env)
            row["window_mc"] = _scores(win.y, model.simulate(win.u, n_paths=mc_paths, seed=seed, y0=y0), win.u, env)
    for key, a in arx.items():
        row[f"whole_{key}"] = _arx_scores(a, whole)
        row[f"window_{key}"] = _arx_scores(a, win, y0=win.y[: a.ny])
    return row


def real_table(model, cfg, data_dir, *, mc_paths: int = 1024, seed: int = 0, max_seconds: float | None = None,
               jobs: int = 1, log=None) -> dict:
    """Score ``model`` on every real record under ``data_dir`` (see the module docstring).

    mc_paths: Monte Carlo paths of the whole-record and window runs (0: linearised only).
    max_seconds: quick mode, the first ``max_seconds`` of each whole record (windows unchanged).
    jobs: records scored in parallel worker processes (joblib; -1: one per core).
    Returns ``{"records": {name: row}, "arx_lags": [...], "mc_paths": int, "seconds": float}``.
    """
    from joblib import Parallel, delayed

    log = log or (lambda m: None)
    t0 = time.perf_counter()
    train = cfg.records_for("train")
    arx = {f"arx_{ny}_{nu}": LinearARX(ny, nu).fit(train) for ny, nu in (ARX_LAGS, (model.ny, model.nu))}
    roles = record_roles(cfg)
    folders = find_records(data_dir)
    if not folders:
        raise ValueError(f"no LMS record (Time.mat + TimeShaker.mat) under {data_dir}")
    todo = [(f, role_of(roles.get(str(f.resolve()), []))) for f in folders]
    rows = {}
    gen = Parallel(n_jobs=jobs, return_as="generator")(
        delayed(_row)(model, arx, f, role, mc_paths, seed, max_seconds) for f, role in todo)
    for (folder, role), row in zip(todo, gen):
        rows[folder.name] = row
        g = row.get("whole_mc", row["whole_linear"])
        log(f"  {folder.name:12s} {role:8s} whole fit {_fmt(g['fit'])} % (linear {_fmt(row['whole_linear']['fit'])}), "
            f"coverage {g['coverage']:.1f} %, peak x{_fmt(g['peak_ratio'], 2)}, diverged {g['diverged_paths']}; "
            f"ARX {_fmt(row['whole_arx_8_4']['fit'])} / {_fmt(row[f'whole_arx_{model.ny}_{model.nu}']['fit'])} %; "
            f"window fit {_fmt(row['window_linear']['fit'])} %")
    # between the recorded frequencies: the model's steady sine response against the rig's FRF
    sines = [f for f in folders if f.parent.name == "Sine"]
    fs = float(cfg.system["fs"])
    frf = (frf_check(model, data_dir, fs=fs, recorded=sines) if max_seconds is None
           else frf_check(model, data_dir, fs=fs, freqs=(12.0, 25.0), seconds=3.0, recorded=sines[:1]))
    if frf is not None:
        log(f"  FRF check: model / rig FRF {min(r['ratio'] for r in frf['rows']):.3f}-"
            f"{max(r['ratio'] for r in frf['rows']):.3f} off resonance")
    return {"records": rows, "arx_lags": [list(ARX_LAGS), [model.ny, model.nu]], "mc_paths": int(mc_paths),
            "max_seconds": max_seconds, "seconds": time.perf_counter() - t0, "frf_check": frf}


def _fmt(v, nd=1) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def table_checks(table: dict) -> dict:
    """The acceptance figures of the table: diverged records, records where the GP-NARX's whole-record
    fit is at least the better ARX's, and the sines' lowest coverage (Monte Carlo when run)."""
    rows = table["records"]
    key = "whole_mc" if table.get("mc_paths") else "whole_linear"
    diverged, wins, cov = [], [], []
    for name, r in rows.items():
        g = r[key]
        lin = r["whole_linear"]
        if any(x["peak_ratio"] is None or x["peak_ratio"] > 3.0 or x["diverged_paths"] > 0 for x in (g, lin)):
            diverged.append(name)
        arx_best = max((r[k]["fit"] for k in r if k.startswith("whole_arx") and r[k]["fit"] is not None),
                       default=-np.inf)
        if g["fit"] is not None and g["fit"] >= arx_best:
            wins.append(name)
        if name.lower().startswith("sine"):
            cov.append(g["coverage"])
    return {"n_records": len(rows), "diverged": diverged, "at_least_arx": len(wins),
            "not_at_least_arx": sorted(set(rows) - set(wins)), "min_sine_coverage": min(cov) if cov else None,
            "scored_with": key}


def markdown(table: dict, checks: dict) -> str:
    """The table as Markdown (docs/results-bert-real.md body)."""
    ny_nu = table["arx_lags"][1]
    mc = table.get("mc_paths")
    head = ("| record | role | whole: fit % (MC) | fit % (lin.) | coverage % | band width [m/s] | peak ratio | "
            f"diverged | out of range | ARX 8/4 fit % | ARX {ny_nu[0]}/{ny_nu[1]} fit % | window: fit % | "
            "coverage % | ARX 8/4 | ARX same lags |\n|" + "---|" * 15)
    lines = [head]
    for name, r in table["records"].items():
        g = r["whole_mc"] if mc else r["whole_linear"]
        w = r["window_mc"] if mc else r["window_linear"]
        lines.append(
            f"| {name} | {r['role']} | {_fmt(g['fit']) if mc else 'n/a'} | {_fmt(r['whole_linear']['fit'])} | "
            f"{g['coverage']:.1f} | {g['band_width']:.3g} | {_fmt(g['peak_ratio'], 2)} | {g['diverged_paths']} | "
            f"{', '.join(g['out_of_range']) or '-'} | {_fmt(r['whole_arx_8_4']['fit'])} | "
            f"{_fmt(r[f'whole_arx_{ny_nu[0]}_{ny_nu[1]}']['fit'])} | {_fmt(w['fit'])} | {w['coverage']:.1f} | "
            f"{_fmt(r['window_arx_8_4']['fit'])} | {_fmt(r[f'window_arx_{ny_nu[0]}_{ny_nu[1]}']['fit'])} |")
    if not mc:
        lines.append("")
        lines.append("Linearised bands only in this run (`--table-mc 0`): the Monte Carlo columns read n/a.")
    lines.append("")
    lines.append(f"Records: {checks['n_records']}; diverged (peak ratio > 3 or diverged paths): "
                 f"{', '.join(checks['diverged']) or 'none'}; GP-NARX whole-record fit at least the better ARX's on "
                 f"{checks['at_least_arx']} of {checks['n_records']}"
                 + (f" (not on {', '.join(checks['not_at_least_arx'])})" if checks["not_at_least_arx"] else "")
                 + f"; lowest sine coverage {_fmt(checks['min_sine_coverage'])} % ({checks['scored_with']}).")
    return "\n".join(lines) + "\n"
