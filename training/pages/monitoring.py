"""docs/results-monitoring.md from the stored runs of three studies (docs/runs/monitoring/): the per-cycle
energy of ``studies.cycle_study`` (``cycles-*.json``), the torque study of ``studies.torque_study``
(``torque.json``) and the real-rig false-alarm study of ``studies.real_monitor_study`` (``real_monitor.json``; the
earlier calibration splits' runs of ``REAL_MONITOR_RUNS``, when stored),
with the facts of the bundles they ran on (``bundles.json``, from the bundles' manifests). Every figure on the
page is a value of those files or computed from them here, so the page cannot drift from its runs
(tests/test_results_pages.py re-renders it).

    python -m studies.monitoring_page docs/runs/monitoring docs/results-monitoring.md
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gpnarx.training.pages.markdown import grouped, lines, load_json, pct, sig, table

# the cycle study's stored runs: (file, label)
CYCLE_RUNS = (("cycles-mc-measured.json", "Monte Carlo, start `measured`"),
              ("cycles-mc-rest.json", "Monte Carlo, start `rest`"),
              ("cycles-linear-measured.json", "linearised, start `measured`"))


def _bundle_line(bundles: dict, ref: str, record: str | None = None) -> str:
    b = (bundles or {}).get(ref)
    if not b:
        return ""
    s = (f"The bundle, `{ref}`, is the one `gpnarx train {b['name']}` writes: ny = {b['lags']['ny']}, "
         f"nu = {b['lags']['nu']}, {b['mode']}" + (f" M = {b['n_inducing']}" if b.get("n_inducing") else "")
         + f", {b['n_train']} training rows")
    if record and (b.get("fits") or {}).get(record) is not None:
        s += f"; fit {pct(b['fits'][record])} % on its `{record}` record"
    return s + ".\n\n"


def cycles_section(run_dir: Path, bundles: dict) -> str:
    runs = [(label, load_json(run_dir, f)) for f, label in CYCLE_RUNS]
    runs = [(label, r) for label, r in runs if r]
    if not runs:
        return ""
    first = runs[0][1]
    sim = first["simulate"]
    out = ("## Per-cycle energy on an independent Bouc-Wen sine\n\n```bash\ngpnarx train bouc-wen --registry R\n"
           f"gpnarx reproduce cycle-study -- --registry R --model bouc-wen --amplitude {sim['amplitude']:g} "
           f"--mc {first['mc_paths']} \\\n    [--start measured|rest] [--method mc|linear] --out RUN.json\n```\n\n"
           f"The study writes the record with `gpnarx simulate bouc-wen --excitation sine --amplitude "
           f"{sim['amplitude']:g}` ({sim['freq']:g} Hz, {sim['n'] / sim['fs']:g} s, steady, noise fraction "
           f"{sim['noise_fraction']:g}), asks `gpnarx loops` for the per-cycle energies ({first['mc_paths']} paths, "
           f"{pct(100 * first['confidence'], 0)} % intervals), and integrates the same input again with the "
           "simulator (`training/simulators/boucwen.py`) for its own loop: the true restoring force R = c v + k y "
           "+ z against the true displacement, over the answer's cycles. "
           + _bundle_line(bundles, first["model"], f"sine-{sim['amplitude']:g}N"))
    rows = []
    for label, r in runs:
        whole, skip = r["cycle_basis"]["n_cycles"], r["cycle_basis"].get("steady_from", 0)
        n = r["n_cycles"]
        rows.append([label, f"{n} / {whole}" + (f" ({skip} start-up cycles left out)" if skip else ""),
                     f"{round(r['coverage_measured'] * n / 100)} ({pct(r['coverage_measured'], 0)} %)",
                     f"{round(r['coverage_simulator'] * n / 100)} ({pct(r['coverage_simulator'], 0)} %)",
                     f"{sig(r['energy_mean'], 4)} J", f"{sig(r['simulator_energy_mean'], 4)} J",
                     f"{pct(100 * r['interval_halfwidth_rel_median'])} %"])
    out += lines(table(["run", "cycles (steady / whole)", "intervals covering the measured energy",
                        "... the simulator's own", "predicted mean energy", "simulator's own",
                        "median half-width of the interval"], rows))
    cyc = first["cycles"]
    picks = sorted({0, 1, len(cyc) // 2, len(cyc) - 1} & set(range(len(cyc))))
    rows = []
    for i in picks:
        c = cyc[i]
        interval = f" ({grouped(c['stiffness_lower'])}-{grouped(c['stiffness_upper'])})" if i == 0 else ""
        rows.append([str(i), f"{c['start']:.4f}-{c['end']:.4f}",
                     f"{sig(c['energy'], 4)} [{sig(c['energy_lower'], 4)}, {sig(c['energy_upper'], 4)}]",
                     sig(c["measured_energy"], 4), sig(c["simulator_energy"], 4), sig(c["drive_work"], 4),
                     grouped(c["stiffness"]) + interval, grouped(c["measured_stiffness"]),
                     grouped(c["simulator_stiffness"]) if i == 0 else ""])
    out += (f"\nSelected cycles ({runs[0][0]}; energies in J, stiffness in N/m):\n\n"
            + lines(table(["cycle", "start-end [s]", "energy [interval]", "measured", "simulator's own", "drive work",
                           "secant stiffness (path interval)", "measured", "simulator's own"], rows)))
    rel = 100 * (first["energy_mean"] / first["simulator_energy_mean"] - 1)
    stiff_rel = 100 * (first["stiffness_mean"] / first["simulator_stiffness_mean"] - 1)
    out += (f"\n- The predicted energy per cycle is {pct(abs(rel))} % {'below' if rel < 0 else 'above'} the "
            f"simulator's own ({sig(first['energy_mean'], 4)} against {sig(first['simulator_energy_mean'], 4)} J); the "
            f"simulator's energy lies inside {pct(first['coverage_simulator'], 0)} % of the cycles' intervals, "
            f"whose median half-width, {pct(100 * first['interval_halfwidth_rel_median'])} %, is the spread of the "
            "Monte Carlo paths' loops. The energy measured from the record's y (the product's `measured_energy`) "
            f"agrees with the simulator's own loop area to {sig(first['max_rel_measured_vs_simulator'], 2)} "
            "(relative, worst cycle).\n")
    for label, r in runs[1:]:
        if r["cycle_basis"].get("steady_from"):
            out += (f"- {label}: the first {r['cycle_basis']['steady_from']} cycles' drive work still includes "
                    "the kinetic energy being built up, so they are left out of `cycles` (`steady_from`).\n")
        if r["method"] == "linear":
            ratio = r["interval_halfwidth_rel_median"] / first["interval_halfwidth_rel_median"]
            out += (f"- {label}: the intervals (energy linear in the output, variance from the output covariance "
                    "the linearised free run propagates over a cycle) have "
                    f"{pct(100 * ratio, 0)} % of the Monte Carlo ones' median width.\n")
    c0 = cyc[0]
    out += (f"- The secant stiffness of the mean loop is {pct(abs(stiff_rel))} % "
            f"{'below' if stiff_rel < 0 else 'above'} the simulator's ({grouped(first['stiffness_mean'])} against "
            f"{grouped(first['simulator_stiffness_mean'])} N/m on average); its interval across paths is wide "
            f"(cycle 0: {grouped(c0['stiffness_lower'])}-{grouped(c0['stiffness_upper'])} N/m), because R = g u - m "
            "x'' holds the second derivative of each path's noise. The energy is the indicator to trend; the "
            "stiffness interval says how little one path's stiffness means.\n\n")
    return out


def _no_run(title: str, study: str, file: str) -> str:
    """A section whose study has no stored run: its name, how to run it, and where its earlier figures went."""
    return (f"## {title}\n\nNo stored run: `gpnarx reproduce {study} -- --help` runs the study; store its `--out` "
            f"JSON as `docs/runs/monitoring/{file}` and re-render this page. The figures published here before came "
            "from no stored run; they are history, in [CHANGELOG.md](../CHANGELOG.md#history-of-published-figures)."
            "\n\n")


def torque_section(t: dict | None, bundles: dict) -> str:
    if not t:
        return _no_run("Energy per cycle against the residual score: torque on the stand-in", "torque-study",
                       "torque.json")
    torques = list(t["per_torque"])
    healthy = f"{t['healthy_torque']:g}"
    out = ("## Energy per cycle against the residual score: torque on the stand-in\n\n```bash\n"
           f"gpnarx train {t['model'].split(':')[0]} --registry R\n"
           f"gpnarx reproduce torque-study -- --registry R --model {t['model'].split(':')[0]} "
           f"--torques {','.join(torques)} --records {t['n_records']} --mc {t['mc_paths']} --out torque.json\n```\n\n"
           f"These are stand-in numbers, never the rig's. The records are {t['n_records']} stand-in realizations "
           "per tightening torque, driven by the monitor's probe (seeds not used by the monitor). Each gets one "
           f"{t['mc_paths']}-path free run of the monitor from its measured outputs. "
           + _bundle_line(bundles, t["model"])
           + "Three indicators are compared: the novelty score; the median measured energy per steady cycle; the "
           f"median ratio of measured to predicted energy per cycle. Each indicator's "
           f"{pct(100 * t['false_alarm_rate_target'], 0)} % threshold is fitted on "
           f"{len(t['thresholds']['calibrated_on_seeds'])} of the {healthy} N m records; the false-alarm rate is "
           f"counted on the other {len(t['thresholds']['false_alarms_on_seeds'])}, and the detection rate on all "
           "records of each other torque. The energy indicators are two-sided.\n\n")
    out += lines(table(
        ["torque [N m]", "records", "flagged by the score", "by the energy", "by the energy ratio", "score (median)",
         "energy per cycle, mean +/- sd [J]", "energy ratio (median)",
         "measured energy inside the predicted interval (median % of cycles)"],
        [[f"{k} (healthy, held-out half)" if k == healthy else k, str(r["n"]), f"{pct(r['flagged_score'], 0)} %",
          f"{pct(r['flagged_energy'], 0)} %", f"{pct(r['flagged_energy_ratio'], 0)} %", sig(r["score_median"], 3),
          f"{sig(r['energy_mean'], 3)} +/- {sig(r['energy_sd'], 2)}", sig(r["energy_ratio_median"], 3),
          pct(r["energy_coverage_median"], 0)] for k, r in t["per_torque"].items()]))
    h = t["per_torque"][healthy]
    others = [k for k in torques if k != healthy]
    lo, hi = min(torques, key=float), max(torques, key=float)
    out += (f"\n- Energy per cycle, {lo} N m to {hi} N m: {sig(t['per_torque'][lo]['energy_mean'], 3)} J to "
            f"{sig(t['per_torque'][hi]['energy_mean'], 3)} J (the stand-in models loosening as lower torque: more "
            "slip).\n"
            f"- Realization scatter of the energy at {healthy} N m: {pct(100 * h['energy_sd'] / h['energy_mean'])} % "
            "of its mean; the shift to each other torque: "
            + ", ".join(f"{k} N m {pct(100 * (t['per_torque'][k]['energy_mean'] / h['energy_mean'] - 1))} %"
                        for k in others) + ".\n"
            f"- Held-out healthy records flagged: score {pct(h['flagged_score'], 0)} %, energy "
            f"{pct(h['flagged_energy'], 0)} %, energy ratio {pct(h['flagged_energy_ratio'], 0)} % (target "
            f"{pct(100 * t['false_alarm_rate_target'], 0)} %, on {h['n']} records: too few to place a tail).\n"
            "- The score says that something changed; the energy, a physical quantity, says which way the joint "
            "changed (loosening raises the dissipation, tightening lowers it).\n\n")
    return out


#: the real-monitor study's stored runs besides ``real_monitor.json`` (the default build's calibration), in the order
#: of the before/after table: (file, label)
REAL_MONITOR_RUNS = (("real_monitor-sparse.json", "earlier split"),
                     ("real_monitor-sparse-linear.json", "earlier split"),
                     ("real_monitor-before.json", "earlier split"),
                     ("real_monitor-gp1.json", "grouped split, propagated band as is"),
                     ("real_monitor.json", "**grouped split (the default build)**"))


def _bundle_of(m: dict, bundles: dict) -> dict:
    """The facts of the bundle a real-monitor run used: stored with the run, else ``bundles.json`` (older runs)."""
    return m.get("bundle") or (bundles or {}).get(f"bert-real:{m['source_version']}") or {}


def _how(m: dict) -> str:
    return f"Monte Carlo, {m['mc_paths']} paths" if m["method"] == "mc" else "linearised"


def real_monitor_section(m: dict | None, bundles: dict, runs: dict | None = None) -> str:
    if not m:
        return _no_run("A real-rig monitor: false alarms on recordings it never saw", "real-monitor-study",
                       "real_monitor.json")
    n, fa = m["n_test"], m["false_alarms"]
    # one-sided 95 % upper bound of a rate with fa events in n trials (exact for fa = 0)
    bound = 1 - 0.05 ** (1 / n) if fa == 0 and n else None
    split = m["split"]

    def spans(d):
        return ", ".join(f"{k} {v[0]:g}-{v[1]:g} s" for k, v in d.items())

    cal_scores = m["calibration_scores"]
    test = [w for w in m["windows"] if any(w["window"].startswith(k) for k in split["test"])]
    off = [w for w in m["windows"] if any(w["window"].startswith(k) for k in split["off_probe"])]
    tscores = sorted(w["score"] for w in test)
    probe = m.get("probe") or {}
    b = _bundle_of(m, bundles)
    cal = split["calibration"]
    out = ("## A real-rig monitor: false alarms on recordings it never saw\n\n```bash\n"
           "gpnarx train bert-real --registry R        # the shipped real-rig model (configs/bert-real.toml)\n"
           "gpnarx reproduce real-monitor-study -- --registry R --mc-check --out real_monitor.json\n```\n\n"
           "The default registry holds this monitor as `bert-real-monitor` (built after `bert-real` when the lab "
           "records are present): the same GP with a novelty threshold and probe contract. The study calibrates it "
           "with the default build's own call (`training.real_monitor.build_real_monitor`: the spike-robust "
           f"`segment_median_rms` score, {_how(m)} free runs from the measured outputs, no refit) and scores "
           "windows the calibration never saw with `gpnarx novelty`. The real BERT subset holds one steady-sine "
           "recording per drive frequency, all at the same torque, so on the rig only the false-alarm rate can be "
           "measured. "
           + (f"The bundle, `bert-real:{b.get('version')}` ({b.get('created')}), is the one `gpnarx train "
              f"bert-real` writes: ny = {b['lags']['ny']}, nu = {b['lags']['nu']}, {b.get('mode')}"
              + (f" M = {b['n_inducing']}" if b.get("n_inducing") else "") + f", {b.get('n_train')} training rows"
              + (f"; band discrepancy scale {sig(b['band_scale'], 3)} of the local amplitude"
                 if b.get("band_scale") else "")
              + (f", propagated band x {sig(b['band_gp_scale'], 3)}" if b.get("band_gp_scale", 1.0) != 1.0 else "")
              + ".\n\n" if b.get("lags") else "\n\n")
           + lines(table(["split", "recordings", "windows", "scores", "verdicts"], [
               ["calibration", f"{len(cal)} recordings, {', '.join(cal)}, each "
                f"{'-'.join(f'{v:g}' for v in next(iter(cal.values())))} s", str(m["n_calibration"]),
                f"{sig(min(cal_scores), 2)}-{sig(max(cal_scores), 2)}",
                f"threshold {sig(m['threshold'], 3)} at a {pct(100 * m['false_alarm_rate_target'], 0)} % target"],
               ["false alarms", spans(split["test"]), str(n),
                f"{sig(tscores[0], 2)}-{sig(tscores[-1], 2)} (median {sig(tscores[len(tscores) // 2], 2)})",
                f"**{fa} novel of {n} ({pct(100 * fa / n, 0)} %)**, {m['test_probe_match']} with `probe_match` true"],
               ["off the probe", spans(split["off_probe"]), str(m["n_off_probe"]),
                f"{sig(min(w['score'] for w in off), 2)}-{sig(max(w['score'] for w in off), 2)}",
                f"{m['off_probe_flagged']} of {m['n_off_probe']} flagged `\"probe\"` in `out_of_range`"]]))
           + "\n")
    if m.get("n_groups"):
        out += (f"- **Why grouped:** the score measures the free run's model-form error, nearly constant within a "
                f"recording and several-fold apart between drive frequencies: in log, a spread of "
                f"{sig(m['log_std_within'], 2)} within a recording against {sig(m['log_std_between'], 2)} between "
                f"the {m['n_groups']} recordings. The threshold is fitted to the spread of a window of a new "
                f"recording (log sd {sig(m['log_std'], 2)}, `model.novelty`), not to more windows of the same "
                "recordings.\n")
    if probe:
        out += f"- **Probe contract it states:** `{json.dumps(probe, sort_keys=True)}`.\n"
    if bound is not None:
        out += (f"- **Confidence of the rate:** 0 of {n} is a false-alarm rate of at most {pct(100 * bound)} % at "
                f"95 % confidence (one-sided, {n} trials): the split is too small to confirm a "
                f"{pct(100 * m['false_alarm_rate_target'], 0)} % target, and windows of one recording are not "
                "independent realizations (same mounting, same day).\n")
    out += ("- **Detection:** how well it detects loosening on the rig cannot be measured with these records; the "
            f"threshold sits {sig(m['threshold'] / float(np.median(cal_scores)), 2)} times the median healthy "
            "calibration score, the price of one threshold over drives whose healthy levels differ.\n")
    checked = m if m.get("mc_check") else next(
        (r for f, _ in reversed(REAL_MONITOR_RUNS[:-1]) if (r := (runs or {}).get(f)) and r.get("mc_check")), None)
    where = next((f for f, _ in REAL_MONITOR_RUNS if (runs or {}).get(f) is checked), None)
    note = "" if checked is m or where is None else (
        f" This check ran on the stored run `{where}` (its bundle and band are in the table above).")
    return out + before_after(m, bundles, runs or {}) + (mc_check(checked, note) if checked else "")


def before_after(m: dict, bundles: dict, runs: dict) -> str:
    """The stored runs of the earlier splits against the default build's (``REAL_MONITOR_RUNS``)."""
    rows = [(runs.get(f), label) for f, label in REAL_MONITOR_RUNS[:-1]] + [(m, REAL_MONITOR_RUNS[-1][1])]
    rows = [(r, label) for r, label in rows if r]
    if len(rows) < 2:
        return ""
    out = ("\n### Before and after: the calibration split\n\nEach row a stored run of the study on the same test "
           "windows (`docs/runs/monitoring/real_monitor*.json`); the earlier split calibrated on 2 s windows of "
           "24-48 s of the 8 and 9.5 Hz recordings alone, one pooled log-normal fit (`--split earlier`). Calibration "
           "wall time on the 2-core development machine shared with other work, with its 1-minute load.\n\n")
    cells = []
    for r, label in rows:
        load = r.get("calibration_load")
        load = f"load {sig(max(load), 2)}" if load else f"load {sig(r.get('load_average'), 2)} at the study's end"
        cells.append([label, f"{_bundle_of(r, bundles).get('mode', 'n/a')} bert-real:{r['source_version']}", _how(r),
                      f"{r['n_calibration']} ({len(r['split']['calibration'])})", sig(r["threshold"], 3),
                      f"**{r['false_alarms']} of {r['n_test']}**", f"{sig(r['calibration_s'], 3)} s, {load}"])
    out += lines(table(["run", "bundle", "propagation", "calibration windows (recordings)", "threshold",
                        "false alarms", "calibration"], cells))

    def key(r):
        return r.get("source_version"), _bundle_of(r, bundles).get("created")

    grouped_runs = [r for r, label in rows if label.startswith(("grouped", "**grouped"))]
    same = [(r, g) for r, label in rows if label == "earlier split" for g in grouped_runs if key(r) == key(g)]
    if same:
        e, g = same[-1]  # an earlier-split run and the grouped run on its bundle
        levels = {}
        for w, sc in zip(e.get("calibration_windows") or [], e["calibration_scores"]):
            levels.setdefault(w.rsplit("_", 1)[0], []).append(sc)
        med = {k: float(np.median(v)) for k, v in levels.items()}
        out += ("\nWith two recordings the pooled fit's spread is whatever lies between those two: on this bundle "
                + ", ".join(f"{k} scores a median {sig(v, 2)}" for k, v in med.items())
                + f", so the earlier split's threshold ({sig(e['threshold'], 3)}) is "
                f"{sig(e['threshold'] / g['threshold'], 2)} times the grouped one and raises {e['false_alarms']} "
                f"false alarms; on the sparse bundle the two lay close together and the threshold fell below the "
                "unseen recordings' level. The grouped split measures that spread over eight recordings.\n")
    return out + "\n"


def mc_check(m: dict, note: str = "") -> str:
    """Linearised against Monte Carlo scores of a few windows (``--mc-check``)."""
    c = m.get("mc_check")
    if not c:
        return ""
    out = (f"### Linearised or Monte Carlo\n\nThe score's band is dominated by the model-discrepancy term (a "
           f"fraction of the predicted amplitude), so a Monte Carlo free run ({c['mc_paths']} paths, two seeds) "
           "changes the score little and costs far more on the exact posterior (`--mc-check`; 1-minute load "
           f"{sig(c['load_average'], 2)} at its end).{note}\n\n")
    out += lines(table(["window", "linearised", "Monte Carlo, seed 0", "seed 1", "wall time linearised / Monte Carlo"],
                       [[w["window"], sig(w["linear"], 3), sig(w["mc_seed0"], 3), sig(w["mc_seed1"], 3),
                         f"{sig(w['linear_s'], 2)} s / {sig(w['mc_s_seed0'], 3)} s"] for w in c["windows"]]))
    return out + "\n"


def render(run_dir) -> str:
    run_dir = Path(run_dir)
    bundles = load_json(run_dir, "bundles.json") or {}
    return ("# Monitoring indicators: per-cycle energy, probe contract, recalibration\n\n"
            "Rendered by `python -m studies.monitoring_page docs/runs/monitoring docs/results-monitoring.md` from "
            "the stored runs in `docs/runs/monitoring/` (the studies' JSON and `bundles.json`, the facts of the "
            "bundles they ran on); do not edit by hand (a test re-renders this page). Each section names the "
            "command that regenerates its run. Definitions: [per-cycle loops](api.md#per-cycle-loops), [probe "
            "contract](api.md#probe-contract), [gpnarx calibrate](cli.md#calibrate).\n\n"
            + cycles_section(run_dir, bundles) + torque_section(load_json(run_dir, "torque.json"), bundles)
            + real_monitor_section(load_json(run_dir, "real_monitor.json"), bundles,
                                   {f: load_json(run_dir, f) for f, _ in REAL_MONITOR_RUNS[:-1]}))


def bundle_facts(bundle_dir) -> dict:
    """What the page says of a bundle, from its manifest: {"NAME:VERSION": lags, mode, rows, fits, ...}."""
    m = json.loads((Path(bundle_dir) / "manifest.json").read_text())
    est = m.get("estimator") or {}
    return {f"{m['name']}:{m['version']}": {
        "name": m["name"], "version": m["version"], "created": m.get("created"), "lags": m["lags"],
        "mode": m["mode"], "n_inducing": est.get("n_inducing") if m["mode"] == "sparse" else None,
        "n_train": m["n_train"], "nlml": m.get("nlml"),
        "fits": {k: v.get("fit") for k, v in m["training"]["records"].items()}}}
