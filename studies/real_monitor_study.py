"""A real-rig novelty monitor with an honest split: calibrated on some recordings, its false alarms
measured on other recordings it never saw (a study script).

    python -m studies.real_monitor_study --registry R [--data DIR] [--method linear|mc] [--mc 128]
        [--split current|earlier] [--mc-check] [--window 2] [--out FILE.json]

The real BERT subset holds one 64 s steady-sine recording per drive frequency, all at 5 N m (no
loosened state), so what can be measured on the rig is the false-alarm rate. The monitor is the
shipped real-rig model (``gpnarx train bert-real``) calibrated by the default build's own code:

1. calibration (``--split current``): ``training.real_monitor.build_real_monitor``, the very call
   that writes ``bert-real-monitor`` in the default registry: 2 s windows of 24-48 s of every 0.15 V
   sine recording from 5 to 9.75 Hz except the test ones, grouped by recording, the spike-robust
   ``segment_median_rms`` score, linearised free runs from the measured outputs (``--method mc``:
   ``--mc`` Monte Carlo paths). ``--split earlier``: the split the monitor had before, 8 and 9.5 Hz
   only, one pooled log-normal fit (``novelty_calibration.calibrate`` without groups), for the
   before/after comparison on the same bundle;
2. false alarms: every window of the steady part (6-50 s) of the 8.5 Hz and 9 Hz recordings,
   which neither the GP's training nor the calibration saw (8.5 Hz is a held-out validation record of
   bert-real; 9 Hz is one of its ``lags`` records), scored with ``gpnarx novelty`` on the monitor with
   the calibration's propagation; the false-alarm rate is the share of 'novel' verdicts;
3. a probe check: windows of the 17 Hz recording, a drive outside the contract, must come back
   with "probe" in out_of_range;
4. ``--mc-check``: a few calibration and test windows scored both linearised and with ``--mc`` Monte
   Carlo paths (two seeds), to show what Monte Carlo would change.

Windows of one recording are not independent realizations (same mounting, same day), so the rate is
quoted with its split and its counts.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gpnarx.model.novelty import novelty_score, novelty_start
from gpnarx.storage.record_files import read_record
from gpnarx.storage.registry import Registry
from gpnarx.training.config import bert_data_dir
from gpnarx.training.novelty_calibration import calibrate
from gpnarx.training.real_monitor import (
    CALIBRATION,
    FALSE_ALARM_RATE,
    MONITOR_NAME,
    OFF_PROBE,
    SCORE_METHOD,
    SOURCE_MODEL,
    TEST,
    build_real_monitor,
)
from gpnarx.training.real_monitor import windows as record_windows
from studies.cli_runner import emit, run_cli

#: the calibration split the monitor had before (8 and 9.5 Hz, one pooled fit): ``--split earlier``
EARLIER_CALIBRATION = {"Sine_08Hz": (24.0, 48.0), "Sine_09p5Hz": (24.0, 48.0)}
#: windows (recording, start [s]) of ``--mc-check``: two calibration, two test
MC_CHECK = (("Sine_08Hz", 24.0), ("Sine_09p5Hz", 24.0), ("Sine_08p5Hz", 24.0), ("Sine_09Hz", 30.0))


def _cli(argv: list[str]) -> dict:
    return run_cli(argv)


def windows(data: Path, spec: dict, width: float, out: Path) -> list[Path]:
    """Write ``width``-second windows of each recording's span as NPZ records; returns their paths."""
    paths = []
    for name, (t0, t1) in spec.items():
        rec = read_record(data / "Sine" / name)
        t = t0
        while t + width <= t1 + 1e-9:
            w = rec.window(t, t + width)
            p = out / f"{name}_{t:05.1f}s.npz"
            np.savez(p, u=w.u, y=w.y, fs=w.fs)
            paths.append(p)
            t += width
    return paths


def _bundle_facts(bundle) -> dict:
    """What the page says about the bundle the study ran on (from its manifest)."""
    m = bundle.manifest
    disc = m.get("band_discrepancy") or {}
    return {"name": m["name"], "version": m["version"], "created": m.get("created"), "mode": m.get("mode"),
            "lags": m.get("lags"), "n_train": m.get("n_train") or (m.get("training") or {}).get("n_train"),
            "band_scale": disc.get("scale"), "band_window_kind": disc.get("window_kind"),
            "band_hold": disc.get("hold"), "band_gp_scale": disc.get("gp_scale", 1.0)}


def mc_check(bundle, data: Path, mc: int, width: float) -> list[dict]:
    """``MC_CHECK`` windows scored linearised and with ``mc`` Monte Carlo paths at seeds 0 and 1 [wall s each]."""
    model, out = bundle.model, []
    for name, t0 in MC_CHECK:
        w = record_windows(data, {name: (t0, t0 + width)}, width)[0]
        y0 = novelty_start(w.y, model.ny)
        row = {"window": w.name}
        t = time.perf_counter()
        run = model.simulate(w.u, method="linear", y0=y0)
        row["linear_s"] = time.perf_counter() - t
        row["linear"] = novelty_score(w.y, run.mean, run.std, SCORE_METHOD)["score"]
        for seed in (0, 1):
            t = time.perf_counter()
            run = model.simulate(w.u, n_paths=mc, seed=seed, method="mc", y0=y0)
            row[f"mc_s_seed{seed}"] = time.perf_counter() - t
            row[f"mc_seed{seed}"] = novelty_score(w.y, run.mean, run.std, SCORE_METHOD)["score"]
        out.append(row)
    return out


def study(registry, model: str = SOURCE_MODEL, data=None, mc: int = 128, width: float = 2.0,
          false_alarm_rate: float = FALSE_ALARM_RATE, workdir=None, method: str = "linear", split: str = "current",
          check_mc: bool = False) -> dict:
    """``method``: the calibration's propagation, 'linear' (the default build's) or 'mc' (``mc`` paths per window);
    the test windows are then scored the same way (the monitor's own default method). ``split``: 'current' (the
    default build's ``build_real_monitor``) or 'earlier' (``EARLIER_CALIBRATION``, ungrouped)."""
    data = Path(data) if data else bert_data_dir()
    work = Path(workdir or tempfile.mkdtemp(prefix="gpnarx-real-monitor-"))
    test = windows(data, TEST, width, work)
    off = windows(data, OFF_PROBE, width, work)
    paths = ["--mc", str(mc)] if method == "mc" else []
    source = Registry(registry).scan().get(model)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    if split == "current":
        if width != 2.0 or model != SOURCE_MODEL or false_alarm_rate != FALSE_ALARM_RATE:
            raise ValueError("--split current is the default build's calibration: 2 s windows of bert-real at a "
                             "0.01 false-alarm rate")
        res = build_real_monitor(Path(registry), data, mc_paths=mc, propagation=method)
        spec = CALIBRATION
    elif split == "earlier":
        spec = EARLIER_CALIBRATION
        res = calibrate(source, record_windows(data, spec, width), Path(registry), false_alarm_rate=false_alarm_rate,
                        score_method=SCORE_METHOD, n_paths=mc, propagation=method, name=MONITOR_NAME)
    else:
        raise ValueError(f"split must be 'current' or 'earlier', got {split!r}")
    calibration_s = time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    nov = res["novelty"]
    ref = f"{res['name']}:{res['version']}"
    scored = []
    for p in test + off:
        a = _cli(["novelty", "--registry", str(registry), "--model", ref, str(p), *paths, "--method", method])
        scored.append({"window": p.stem, "score": a["score"], "verdict": a["verdict"], "probe_match": a["probe_match"],
                       "out_of_range": a["out_of_range"], "drive_frequency": a["drive"]["frequency"]})
    on = [s for s in scored if any(s["window"].startswith(k) for k in TEST)]
    offp = [s for s in scored if any(s["window"].startswith(k) for k in OFF_PROBE)]
    novel = [s for s in on if s["verdict"] == "novel"]
    out = {"model": ref, "source_version": res["source_version"], "bundle": _bundle_facts(source), "method": method,
           "mc_paths": mc if method == "mc" else 0, "window_s": width, "split_name": split,
           "calibration_s": calibration_s, "calibration_load": [load0, load1], "load_average": os.getloadavg()[0],
           "split": {"calibration": {k: list(v) for k, v in spec.items()},
                     "test": {k: list(v) for k, v in TEST.items()},
                     "off_probe": {k: list(v) for k, v in OFF_PROBE.items()}},
           "threshold": nov["threshold"], "false_alarm_rate_target": nov["false_alarm_rate"],
           "n_calibration": nov["n_healthy"], "n_groups": nov.get("n_groups"),
           "log_std_between": nov.get("log_std_between"), "log_std_within": nov.get("log_std_within"),
           "log_std": nov["log_std"], "probe": nov["probe"],
           "calibration_scores": [r["score"] for r in res["records"]],
           "calibration_windows": [r["name"] for r in res["records"]],
           "n_test": len(on), "false_alarms": len(novel),
           "false_alarm_rate_measured": len(novel) / len(on) if on else None,
           "test_probe_match": sum(bool(s["probe_match"]) for s in on),
           "off_probe_flagged": sum("probe" in s["out_of_range"] for s in offp), "n_off_probe": len(offp),
           "test_score_max": max(s["score"] for s in on) if on else None,
           "windows": scored}
    if check_mc:
        out["mc_check"] = {"mc_paths": mc, "windows": mc_check(source, data, mc, width),
                           "load_average": os.getloadavg()[0]}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.real_monitor_study",
                                description=__doc__.splitlines()[0])
    p.add_argument("--registry", required=True)
    p.add_argument("--model", default=SOURCE_MODEL)
    p.add_argument("--data", default=None, help="the BERT records (default: $GPNARX_BERT_DATA or ../shared/data)")
    p.add_argument("--mc", type=int, default=128, help="Monte Carlo paths per window (--method mc, --mc-check)")
    p.add_argument("--method", choices=("linear", "mc"), default="linear",
                   help="propagation of the calibration and of the test windows' scores (default: the build's)")
    p.add_argument("--split", choices=("current", "earlier"), default="current",
                   help="the default build's calibration, or the earlier 8 and 9.5 Hz one (pooled fit)")
    p.add_argument("--mc-check", action="store_true", dest="check_mc",
                   help="also score a few windows linearised and with --mc paths (two seeds)")
    p.add_argument("--window", type=float, default=2.0)
    p.add_argument("--false-alarm-rate", type=float, default=FALSE_ALARM_RATE, dest="far")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    res = study(a.registry, a.model, a.data, a.mc, a.window, a.far, method=a.method, split=a.split,
                check_mc=a.check_mc)
    return emit(res, a.out)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
