"""The real-rig results table by excitation class: every real record of a data folder, whole and from
rest, GP-NARX next to two linear ARX baselines a system-identification engineer would take seriously.

For each record found under the data folder (LMS exports with ``Time.mat`` + ``TimeShaker.mat``; records
a user adds there are picked up too), its excitation class (``record_class``: sine near the first
resonance, sine away from it, sweep, broadband noise) and its role in the dataset config (``train`` when
any training window comes from it, ``lags`` when it took part in a choice, ``validate`` when it is held
out of every choice, ``unseen`` when the config does not name it):

* the whole record free-run from rest (start-up, steady state or sweep, free decay after the drive
  stops), by the linearised method and, unless skipped, by a Monte Carlo run (``mc_paths`` paths):
  fit % (eq. 14), peak ratio max|mean| / max|y| (divergence shows as a ratio far above 1), coverage
  of the 99 % predictive band, the band's mean half-width over the record's standard deviation,
  diverged paths and the out-of-range flags (``model.envelope``);
* ARX by lag search: the linear ARX whose order the GP-NARX's own lag search chooses (the same grid,
  the same ``lags`` records, the same criterion) fitted on the same training records
  (``baselines.arx_lag_search``);
* ARX of the class: a linear ARX (ny = nu = ``CLASS_ARX_LAGS``) fitted by least squares on the other
  records of the record's class in the data folder, whole (the noise runs for a noise run, the sweeps
  for a sweep), never on the record it is scored on;
* sharpness: the band's mean half-width over that of a calibrated 99 % band around the class ARX's
  errors on the record (2.576 x its RMS error): a band wider than a linear model's honest one tells a
  monitor little;
* between the recorded frequencies, the model's steady sine response against the rig's own FRF
  (``studies.frf_check``), when a noise run's LMS ``FRF.mat`` is in the data folder.

Units: u [V], y [m/s], times [s]. The numbers come from the run that writes them.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gpnarx.model.envelope import assess
from gpnarx.model.metrics import band_width, coverage, fit_percent
from gpnarx.model.probe import drive_of
from gpnarx.model.record import Record
from gpnarx.storage.record_files import read_record
from gpnarx.training.baselines import LinearARX, arx_lag_search
from gpnarx.training.checkout import call_study
from studies.frf_check import RESONANCE_BAND, frf_check

CLASSES = ("sine near resonance", "sine away from resonance", "sweep", "noise")
CLASS_ARX_LAGS = (16, 16)  # the class ARX's order (ny, nu): the order a user fits a noise run with first
SINE_SHARE = 0.5  # share of u's variance in its dominant sine from which a record counts as a sine
Z99 = 2.5758  # two-sided 99 % normal quantile: a calibrated 99 % band is +/- Z99 x the RMS error
TARGETS = {"min_coverage": 90.0, "max_noise_sharpness": 1.5}  # held-out records: per class, and noise runs


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


def record_class(folder: Path, rec: Record) -> str:
    """The excitation class of a real record (one of ``CLASSES``): a sweep when a folder of its path is
    named Chirp* or Sweep*, a sine when the sine at u's dominant frequency holds at least ``SINE_SHARE`` of
    u's variance (``model.probe.drive_of``; a whole 64 s sine record is driven for 51 s, so about 0.8;
    a sweep or a noise run below 0.01), near resonance when
    the sine's frequency lies in ``frf_check.RESONANCE_BAND``; otherwise broadband noise."""
    parts = [p.lower() for p in Path(folder).parts]
    if any(p.startswith(("chirp", "sweep")) for p in parts):
        return "sweep"
    d = drive_of(rec.u, rec.fs)
    if d["frequency"] is not None and d["concentration"] >= SINE_SHARE:
        lo, hi = RESONANCE_BAND
        return "sine near resonance" if lo <= d["frequency"] <= hi else "sine away from resonance"
    return "noise"


def _scores(y, run, u, env) -> dict:
    mean = run.mean
    with np.errstate(all="ignore"):
        f = fit_percent(y, mean)
        peak = float(np.max(np.abs(mean)) / max(float(np.max(np.abs(y))), 1e-300))
        half = float(np.mean(run.upper - run.lower) / 2.0)
    out = {"fit": float(f) if np.isfinite(f) else None, "peak_ratio": peak if np.isfinite(peak) else None,
           "coverage": coverage(y, run.lower, run.upper), "band_width": band_width(run.lower, run.upper),
           "half_width": half if np.isfinite(half) else None,
           "half_width_over_std": half / float(np.std(y)) if np.isfinite(half) and np.std(y) > 0 else None,
           "seconds": float(run.seconds)}
    out.update(assess(env, run, u, y))
    return out


def _arx_scores(arx: LinearARX | None, rec: Record) -> dict:
    if arx is None:
        return {"fit": None, "rmse": None, "peak_ratio": None}
    with np.errstate(all="ignore"):
        yh = arx.simulate(rec.u)
        f = fit_percent(rec.y, yh)
        e = float(np.sqrt(np.mean((rec.y - yh) ** 2)))
        peak = float(np.max(np.abs(yh)) / max(float(np.max(np.abs(rec.y))), 1e-300))
    fin = np.isfinite
    return {"fit": float(f) if fin(f) else None, "rmse": e if fin(e) else None,
            "peak_ratio": peak if fin(peak) else None}


def _row(model, arx_search, arx_class, folder: Path, rec: Record, role: str, cls: str, mc_paths: int, seed: int,
         max_seconds) -> dict:
    """One record's row (see the module docstring); runs in a worker process when jobs > 1."""
    env = getattr(model, "envelope_", None)
    whole = rec if not max_seconds else rec.window(0.0, min(max_seconds, rec.n / rec.fs))
    row = {"role": role, "class": cls, "seconds_long": whole.n / whole.fs,
           "measured_peak": float(np.max(np.abs(whole.y))), "measured_std": float(np.std(whole.y)),
           "input_peak": float(np.max(np.abs(whole.u)))}
    with np.errstate(all="ignore"):
        row["whole_linear"] = _scores(whole.y, model.simulate(whole.u, method="linear"), whole.u, env)
        if mc_paths:
            row["whole_mc"] = _scores(whole.y, model.simulate(whole.u, n_paths=mc_paths, seed=seed), whole.u, env)
    row["arx_search"] = _arx_scores(arx_search, whole)
    row["arx_class"] = {**_arx_scores(arx_class[0] if arx_class else None, whole),
                        "trained_on": arx_class[1] if arx_class else []}
    ref = row["arx_class"]["rmse"]
    for key in ("whole_linear", "whole_mc"):
        if key in row:
            h = row[key]["half_width"]
            row[key]["sharpness"] = h / (Z99 * ref) if h is not None and ref else None
    return row


def add_mc_rows(model, table: dict, data_dir, names, mc_paths: int, seed: int = 0, log=None) -> dict:
    """Add the Monte Carlo scores (``whole_mc``, with its sharpness against the row's class ARX) of the records
    ``names`` to a linearised-only ``table`` (``real_table(mc_paths=0)``), for a model whose Monte Carlo
    runs are too costly for every record; ``table["mc_records"]`` names them and the checks count them only."""
    env = getattr(model, "envelope_", None)
    folders = {p.name: p for p in find_records(data_dir)}
    for name in names:
        rec, row = read_record(folders[name]), table["records"][name]
        with np.errstate(all="ignore"):
            g = _scores(rec.y, model.simulate(rec.u, n_paths=mc_paths, seed=seed), rec.u, env)
        ref, h = row["arx_class"]["rmse"], g["half_width"]
        g["sharpness"] = h / (Z99 * ref) if h is not None and ref else None
        row["whole_mc"] = g
        if log:
            log(f"  {name}: {mc_paths}-path Monte Carlo fit {_fmt(g['fit'])} %, coverage {g['coverage']:.1f} %, "
                f"{g['seconds']:.0f} s")
    table["mc_paths"] = int(mc_paths)
    table["mc_records"] = list(dict.fromkeys([*table.get("mc_records", []), *names]))  # earlier rows kept
    return table


def add_residual_rows(model, table: dict, data_dir, lags: int = 25, log=None) -> dict:
    """Add each record's one-step residual tests (``model.residual_tests.one_step_check``: the one-step fit, the
    residuals' autocorrelation and their cross-correlation with u at lags 1..``lags`` / -lags..lags with 99 %
    limits, Ljung-Box and its cross-correlation counterpart) to ``table`` as ``row["one_step"]`` (the
    correlations themselves left out: their shares, largest values and p-values kept)."""
    from gpnarx.model.residual_tests import one_step_check

    folders = {p.name: p for p in find_records(data_dir)}
    for name, row in table["records"].items():
        rec = read_record(folders[name])
        if table.get("max_seconds"):
            rec = rec.window(0.0, min(table["max_seconds"], rec.n / rec.fs))
        chk = one_step_check(model, rec.u, rec.y, lags=lags)
        t = chk["residual_tests"]
        ac, xc = t["autocorrelation"], t["cross_correlation"]
        ix = int(np.argmax(np.abs(xc["r"])))
        row["one_step"] = {"fit": chk["fit"], "rmse": chk["rmse"], "lags": t["lags"], "limit": t["limit"],
                           "auto_outside": ac["n_outside"], "auto_max": float(np.max(np.abs(ac["r"]))),
                           "ljung_box_p": ac["ljung_box"]["p_value"], "white": ac["white"],
                           "cross_outside": xc["n_outside"], "cross_n": len(xc["r"]),
                           "cross_max": float(abs(xc["r"][ix])), "cross_max_lag": int(xc["lag"][ix]),
                           "cross_p": xc["portmanteau"]["p_value"], "independent": xc["independent"]}
        if log:
            log(f"  {name}: one-step fit {chk['fit']:.1f} %, autocorrelation {ac['n_outside']}/{t['lags']} lags "
                f"outside, cross-correlation {xc['n_outside']}/{len(xc['r'])}")
    table["residual_lags"] = int(lags)
    return table


#: prediction horizons k [samples] of the k-step fit table (``add_kstep_rows``), besides the free run
KSTEP_HORIZONS = (1, 8, 64, 512)


def add_kstep_rows(model, table: dict, data_dir, horizons=KSTEP_HORIZONS, log=None) -> dict:
    """Add each record's k-step-ahead fits to ``table`` as ``row["k_step"]``: the whole record linearised,
    ``GPNARX.simulate(u, y=y, horizon=k)`` (the run restarted from the measured outputs every k samples,
    ``model.freerun.horizon``) for each k of ``horizons`` [samples], and the free run from the measured start
    (``y0`` = the first ny samples: the k-step prediction whose k is the record's length); fit % (eq. 14) and
    coverage % of the 99 % band (eqs. 8-9 propagated over at most k steps; the free run's adds the discrepancy
    term), each scored on every sample. ``table["kstep_horizons"]`` names the horizons."""
    folders = {p.name: p for p in find_records(data_dir)}
    for name, row in table["records"].items():
        rec = read_record(folders[name])
        if table.get("max_seconds"):
            rec = rec.window(0.0, min(table["max_seconds"], rec.n / rec.fs))
        t0 = time.perf_counter()
        out = {}
        with np.errstate(all="ignore"):
            for k in horizons:
                run = model.simulate(rec.u, y=rec.y, horizon=int(k), method="linear")
                out[str(k)] = {"fit": _finite(fit_percent(rec.y, run.mean)),
                               "coverage": coverage(rec.y, run.lower, run.upper)}
            run = model.simulate(rec.u, y0=rec.y[: model.ny], method="linear")
            out["free_run"] = {"fit": _finite(fit_percent(rec.y, run.mean)),
                               "coverage": coverage(rec.y, run.lower, run.upper)}
        out["seconds"] = time.perf_counter() - t0
        row["k_step"] = out
        if log:
            log(f"  {name}: k-step fit " + ", ".join(f"k={k} {_fmt(out[str(k)]['fit'])} %" for k in horizons)
                + f", free run {_fmt(out['free_run']['fit'])} % ({out['seconds']:.0f} s)")
    table["kstep_horizons"] = [int(k) for k in horizons]
    return table


def _finite(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def kstep_markdown(table: dict) -> str:
    """The k-step fits of ``add_kstep_rows`` as Markdown, by class: fit % (coverage %) by horizon."""
    ks = [str(k) for k in table.get("kstep_horizons", KSTEP_HORIZONS)]
    order = {c: i for i, c in enumerate(CLASSES)}
    lines = ["| record | class | role | " + " | ".join(f"k = {k}" for k in ks) + " | free run (measured start) |",
             "|" + "---|" * (4 + len(ks))]
    for name, r in sorted(table["records"].items(), key=lambda kv: (order.get(kv[1]["class"], 9), kv[0])):
        o = r.get("k_step")
        if not o:
            continue
        cells = [f"{_fmt(o[k]['fit'])} ({o[k]['coverage']:.1f})" for k in [*ks, "free_run"]]
        lines.append(f"| {name} | {r['class']} | {r['role']} | " + " | ".join(cells) + " |")
    rows = {n: r for n, r in table["records"].items() if r.get("k_step")}
    held = {n: r for n, r in rows.items() if r["role"] in ("validate", "unseen")}
    if held:
        med = ", ".join(f"{'k = ' + k if k != 'free_run' else 'free run'} "
                        f"{_fmt(float(np.median([r['k_step'][k]['fit'] for r in held.values()])))} %"
                        for k in [*ks, "free_run"])
        low = []
        for k in [*ks, "free_run"]:
            name = min(rows, key=lambda n: rows[n]["k_step"][k]["coverage"])
            low.append(f"{'k = ' + k if k != 'free_run' else 'free run'} {rows[name]['k_step'][k]['coverage']:.1f} % "
                       f"({name})")
        lines += ["", f"Median fit over the {len(held)} held-out records (validate, unseen): {med}. Lowest coverage "
                      f"by horizon over every record: {'; '.join(low)}."]
        if len(ks) > 1:
            a, b = ks[0], ks[1]
            better = sorted(n for n, r in rows.items() if r["k_step"][b]["fit"] > r["k_step"][a]["fit"])
            if better:
                lines += ["", f"Records where k = {b} fits better than k = {a}: {', '.join(better)}. A likely "
                              f"cause: there the measured outputs fed in as lags carry more error (sensor noise on a "
                              f"small response) than the model's own prediction of them a few steps on."]
    return "\n".join(lines) + "\n"


#: the gap cut out of the gap record (``gap_record``) [s], from its middle
GAP_SECONDS = 0.5


def gap_record(model, data_dir, out_dir, name: str = "Sine_20Hz", seconds: float | None = 16.0,
               gap: float = GAP_SECONDS) -> dict:
    """A real record with ``gap`` s cut out of its middle (u and y set to NaN there: a dropout), predicted
    (``GPNARX.simulate(u, y=y)``, linearised: the answer NaN through the gap, the run restarted from the measured
    outputs after it) against the same record whole, both from rest; fit % and coverage % skip the gap
    (``metrics.summary``), and also on the samples after the gap alone. ``seconds``: the record's first seconds
    (None: whole). A figure (``gap_record.png`` in ``out_dir``) shows the measured output, both means and the
    band around the gap. Returns the figures (``figure``: the PNG's file name)."""
    from gpnarx.model.gaps import find_gaps
    from gpnarx.model.metrics import summary

    folders = {p.name: p for p in find_records(data_dir)}
    rec = read_record(folders[name])
    if seconds:
        rec = rec.window(0.0, min(seconds, rec.n / rec.fs))
    n, fs = rec.n, rec.fs
    a = n // 2 - int(round(gap * fs)) // 2
    b = a + int(round(gap * fs))
    u, y = rec.u.copy(), rec.y.copy()
    u[a:b] = np.nan
    y[a:b] = np.nan
    whole = model.simulate(rec.u, method="linear")
    cut = model.simulate(u, y=y, method="linear")
    after = slice(b, n)
    out = {"record": name, "seconds": n / fs, "fs": fs, "gaps": [[g0, g1] for g0, g1 in find_gaps(u, y)],
           "gap_seconds": (b - a) / fs, "gap_start_s": a / fs, "gap_end_s": b / fs,
           "nan_through_gap": bool(np.all(np.isnan(cut.mean[a:b]))),
           "cut": summary(rec.y, cut.mean, cut.lower, cut.upper),
           "whole": summary(rec.y, np.where(np.isnan(cut.mean), np.nan, whole.mean), whole.lower, whole.upper),
           "cut_after": summary(rec.y[after], cut.mean[after], cut.lower[after], cut.upper[after]),
           "whole_after": summary(rec.y[after], whole.mean[after], whole.lower[after], whole.upper[after]),
           "figure": "gap_record.png"}
    _gap_figure(Path(out_dir) / out["figure"], rec, whole, cut, a, b)
    return out


def _gap_figure(path: Path, rec: Record, whole, cut, a: int, b: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fs = rec.fs
    lo, hi = max(0, a - int(0.5 * fs)), min(rec.n, b + int(1.0 * fs))
    t = np.arange(lo, hi) / fs
    fig, ax = plt.subplots(figsize=(9, 3.6))
    ax.plot(t, rec.y[lo:hi], color="k", lw=0.8, label="measured y (in the gap: what was cut out of u and y)")
    ax.plot(t, whole.mean[lo:hi], color="tab:blue", lw=0.8, alpha=0.7, label="record whole: free run from rest")
    ax.fill_between(t, cut.lower[lo:hi], cut.upper[lo:hi], color="tab:orange", alpha=0.3, lw=0)
    ax.plot(t, cut.mean[lo:hi], color="tab:orange", lw=1.0, label="record with the gap: 99 % band and mean")
    ax.axvspan(a / fs, b / fs, color="0.85", zorder=0, label=f"gap ({(b - a) / fs:.2f} s)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"y [{rec.units.get('y') or 'm/s'}]")
    ax.set_title(f"{rec.name}: {(b - a) / fs:.1f} s cut out of its middle, predicted (linearised)")
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def gap_markdown(g: dict) -> str:
    """The gap record of ``gap_record`` as Markdown (a table and its figure)."""
    rows = [("record with the gap", g["cut"], g["cut_after"]), ("record whole", g["whole"], g["whole_after"])]
    lines = ["| prediction | fit % | coverage % | fit % after the gap | coverage % after the gap |",
             "|---|---|---|---|---|"]
    for label, s, t in rows:
        lines.append(f"| {label} | {_fmt(s['fit'])} | {s['coverage']:.1f} | {_fmt(t['fit'])} | {t['coverage']:.1f} |")
    return ("\n".join(lines) + f"\n\n![{g['record']} with a gap](runs/bert-real/{g['figure']})\n")


def residual_markdown(table: dict) -> str:
    """The residual tests of ``add_residual_rows`` as Markdown, by class."""
    order = {c: i for i, c in enumerate(CLASSES)}
    lines = ["| record | class | role | one-step fit % | autocorr. lags outside | largest abs r | Ljung-Box p | "
             "cross-corr. lags outside | largest abs r_ue (lag) | cross-corr. p |", "|" + "---|" * 10]
    for name, r in sorted(table["records"].items(), key=lambda kv: (order.get(kv[1]["class"], 9), kv[0])):
        o = r.get("one_step")
        if not o:
            continue
        lines.append(f"| {name} | {r['class']} | {r['role']} | {o['fit']:.1f} | {o['auto_outside']}/{o['lags']} | "
                     f"{o['auto_max']:.2f} | {o['ljung_box_p']:.2g} | {o['cross_outside']}/{o['cross_n']} | "
                     f"{o['cross_max']:.2f} ({o['cross_max_lag']:+d}) | {o['cross_p']:.2g} |")
    return "\n".join(lines) + "\n"


def _class_arx(recs: dict, classes: dict) -> dict:
    """{record name: (ARX fitted on the other records of its class, their names)} (None: no other record)."""
    out = {}
    for name, cls in classes.items():
        others = [n for n, c in classes.items() if c == cls and n != name]
        out[name] = (LinearARX(*CLASS_ARX_LAGS).fit([recs[n] for n in others]), others) if others else None
    return out


def real_table(model, cfg, data_dir, *, mc_paths: int = 1024, seed: int = 0, max_seconds: float | None = None,
               jobs: int = 1, lag_grid=None, lag_criterion: str = "worst", log=None) -> dict:
    """Score ``model`` on every real record under ``data_dir`` (see the module docstring).

    mc_paths: Monte Carlo paths of the whole-record runs (0: linearised only).
    max_seconds: quick mode, the first ``max_seconds`` of each record.
    jobs: records scored in parallel worker processes (joblib; -1: one per core).
    lag_grid: (ny values, nu values) of the ARX lag search (default: the model's own lags only);
    lag_criterion: its choice rule ("worst" or "mean" fit over the config's ``lags`` records).
    Returns ``{"records": {name: row}, "arx_search": {...}, "mc_paths": int, "seconds": float, ...}``.
    """
    from joblib import Parallel, delayed

    log = log or (lambda m: None)
    t0 = time.perf_counter()
    train, lags = cfg.records_for("train"), cfg.records_for("lags")
    grid = lag_grid or ([model.ny], [model.nu])
    search = arx_lag_search(train, lags, grid[0], grid[1], criterion=lag_criterion)
    log(f"  ARX by the lag search: ny={search['ny']} nu={search['nu']} ({lag_criterion} fit {search['fit']:.1f} % "
        f"on the 'lags' records)")
    roles = record_roles(cfg)
    folders = find_records(data_dir)
    if not folders:
        raise ValueError(f"no LMS record (Time.mat + TimeShaker.mat) under {data_dir}")
    recs = {f.name: read_record(f) for f in folders}
    classes = {f.name: record_class(f, recs[f.name]) for f in folders}
    class_arx = _class_arx(recs, classes)
    todo = [(f, role_of(roles.get(str(f.resolve()), []))) for f in folders]
    rows = {}
    gen = Parallel(n_jobs=jobs, return_as="generator")(
        delayed(call_study)("real_table", "_row", model, search["model"], class_arx[f.name], f, recs[f.name], role,
                            classes[f.name], mc_paths, seed, max_seconds) for f, role in todo)
    for (folder, role), row in zip(todo, gen):
        rows[folder.name] = row
        g = row.get("whole_mc", row["whole_linear"])
        log(f"  {folder.name:12s} {row['class']:24s} {role:8s} fit {_fmt(g['fit'])} % (linear "
            f"{_fmt(row['whole_linear']['fit'])}), coverage {g['coverage']:.1f} %, half-width/std "
            f"{_fmt(g['half_width_over_std'], 2)}, peak x{_fmt(g['peak_ratio'], 2)}, diverged {g['diverged_paths']}; "
            f"ARX search {_fmt(row['arx_search']['fit'])} %, class {_fmt(row['arx_class']['fit'])} %")
    # between the recorded frequencies: the model's steady sine response against the rig's FRF
    sines = [f for f in folders if classes[f.name].startswith("sine")]
    fs = float(cfg.system["fs"])
    frf = (frf_check(model, data_dir, fs=fs, recorded=sines) if max_seconds is None
           else frf_check(model, data_dir, fs=fs, freqs=(12.0, 25.0), seconds=3.0, recorded=sines[:1]))
    if frf is not None:
        log(f"  FRF check: model / rig FRF {min(r['ratio'] for r in frf['rows']):.3f}-"
            f"{max(r['ratio'] for r in frf['rows']):.3f} off resonance")
    arx_search = {k: v for k, v in search.items() if k != "model"}
    return {"records": rows, "arx_search": arx_search, "class_arx_lags": list(CLASS_ARX_LAGS),
            "mc_paths": int(mc_paths), "mc_records": [n for n, r in rows.items() if "whole_mc" in r],
            "max_seconds": max_seconds, "seconds": time.perf_counter() - t0,
            "frf_check": frf, "targets": dict(TARGETS)}


def _fmt(v, nd=1) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def _methods(table: dict) -> list[str]:
    return ["whole_linear", "whole_mc"] if table.get("mc_paths") else ["whole_linear"]


def table_checks(table: dict) -> dict:
    """The acceptance figures of the table, for each method run (linearised; Monte Carlo when run):
    diverged records; held-out records whose fit is at least the better ARX's; per class, the lowest
    held-out coverage; the noise runs' largest sharpness ratio; and ``met``: every held-out record at
    least the better ARX, every class's held-out coverage at least 90 %, every noise run's sharpness at
    most 1.5."""
    rows = table["records"]
    diverged = sorted({n for n, r in rows.items() for k in _methods(table) if k in r
                       and (r[k]["peak_ratio"] is None or r[k]["peak_ratio"] > 3.0 or r[k]["diverged_paths"] > 0)})
    out = {"n_records": len(rows), "diverged": diverged, "held_out": sorted(n for n, r in rows.items()
                                                                          if r["role"] == "validate"),
           "methods": {}}
    met = not diverged
    for key in _methods(table):
        below_arx, cov, sharp, scored = [], {}, {}, 0
        for name, r in rows.items():
            if key not in r:  # a Monte Carlo pass run on some records only (``add_mc_rows``)
                continue
            g, scored = r[key], scored + 1
            if r["class"] == "noise" and g.get("sharpness") is not None:
                sharp[name] = g["sharpness"]
            if r["role"] != "validate":
                continue
            best = max((x for x in (r["arx_search"]["fit"], r["arx_class"]["fit"]) if x is not None),
                       default=-np.inf)
            if g["fit"] is None or g["fit"] < best:
                below_arx.append(name)
            cov.setdefault(r["class"], []).append(g["coverage"])
        m = {"n_scored": scored, "below_better_arx": below_arx,
             "min_heldout_coverage": {c: min(v) for c, v in cov.items()},
             "max_noise_sharpness": max(sharp.values()) if sharp else None, "noise_sharpness": sharp}
        sharp_max = m["max_noise_sharpness"]
        m["met"] = (not below_arx and all(v >= TARGETS["min_coverage"] for v in m["min_heldout_coverage"].values())
                    and (sharp_max is None or sharp_max <= TARGETS["max_noise_sharpness"]))
        met = met and m["met"]
        out["methods"][key] = m
    out["met"] = met
    return out


def markdown(table: dict, checks: dict) -> str:
    """The table by class as Markdown (the body of docs/results-bert-real.md)."""
    mc = bool(table.get("mc_paths"))
    s = table["arx_search"]
    head = ("| record | class | role | fit % (lin.) | fit % (MC) | ARX search fit % | ARX class fit % | "
            "coverage % (lin.) | coverage % (MC) | half-width / std (lin.) | sharpness (lin.) | sharpness (MC) | "
            "peak ratio | diverged | out of range |\n|" + "---|" * 15)
    lines = [head]
    order = {c: i for i, c in enumerate(CLASSES)}
    for name, r in sorted(table["records"].items(), key=lambda kv: (order.get(kv[1]["class"], 9), kv[0])):
        lin = r["whole_linear"]
        g = r.get("whole_mc", {})
        flags = sorted(set(lin["out_of_range"]) | set(g.get("out_of_range", [])))
        lines.append(
            f"| {name} | {r['class']} | {r['role']} | {_fmt(lin['fit'])} | {_fmt(g.get('fit')) if mc else 'n/a'} | "
            f"{_fmt(r['arx_search']['fit'])} | {_fmt(r['arx_class']['fit'])} | {lin['coverage']:.1f} | "
            f"{_fmt(g.get('coverage')) if mc else 'n/a'} | {_fmt(lin['half_width_over_std'], 2)} | "
            f"{_fmt(lin.get('sharpness'), 2)} | {_fmt(g.get('sharpness'), 2) if mc else 'n/a'} | "
            f"{_fmt(lin['peak_ratio'], 2)} | {max(lin['diverged_paths'], g.get('diverged_paths', 0))} | "
            f"{', '.join(flags) or '-'} |")
    if not mc:
        lines.append("")
        lines.append("Linearised bands only in this run (`--table-mc 0`): the Monte Carlo columns read n/a.")
    lines.append("")
    lines.append(f"ARX search: ny={s['ny']}, nu={s['nu']}, chosen by the GP-NARX's lag search ({s['criterion']} fit "
                 f"{s['fit']:.1f} % on the `lags` records) and fitted on the same training records. ARX class: "
                 f"ny=nu={table['class_arx_lags'][0]}, fitted on the other records of the class in the data folder. "
                 "Sharpness: mean band half-width / (2.576 x the class ARX's RMS error on the record).")
    lines.append("")
    lines.append(f"Records: {checks['n_records']}; diverged (peak ratio > 3 or diverged paths): "
                 f"{', '.join(checks['diverged']) or 'none'}.")
    for key, m in checks["methods"].items():
        label = "linearised" if key == "whole_linear" else f"{table['mc_paths']}-path Monte Carlo"
        if m.get("n_scored", checks["n_records"]) < checks["n_records"]:
            label += f" (on the {m['n_scored']} records it ran on: {', '.join(table.get('mc_records', []))})"
        covs = ", ".join(f"{c} {v:.1f} %" for c, v in m["min_heldout_coverage"].items())
        lines.append(f"- {label}: held-out records below the better ARX's fit: "
                     f"{', '.join(m['below_better_arx']) or 'none'}; lowest held-out coverage by class: {covs}; "
                     f"noise sharpness at most {_fmt(m['max_noise_sharpness'], 2)} (target 1.5); "
                     f"targets {'met' if m['met'] else 'NOT met'}.")
    if table.get("mc_note"):  # where some Monte Carlo rows came from (add_mc_rows on another run's bundle)
        lines.append("")
        lines.append(str(table["mc_note"]))
    return "\n".join(lines) + "\n"
