"""``gpnarx update`` with one new record against ``gpnarx train`` of the same model, same run.

Product: the process ``gpnarx update NAME RECORD --window START:END --registry R --json`` on the version the train
just wrote: the monitor's judgement, the rank update of the exact posterior (``GPNARX.partial_fit``), the noise, band
and novelty recalibrations of its config and the new version written (``training.update``).

Baseline: the process ``gpnarx train CONFIG --registry R --json`` that wrote the model (ML-II, the same
recalibrations, the evaluation of every scored record, the report), timed in the same run on the same machine.
The update is the cheaper alternative to a retrain on the grown data, so ``ratio=`` is update / train wall time
(lower is better; issue 53's target: at most 0.1). ``rank_update_s=``, ``noise_s=``, ``band_s=`` and
``novelty_s=`` are the update's steps as it reports them (``seconds`` of its ``--json``).

Full run: the shipped ``bert-real`` config (lab data in $GPNARX_BERT_DATA or ../shared/data/bert-t5nm) and one
16 s record, the 19 Hz sine from 24 to 40 s (the training windows of that sine are 0-4, 20-22 and 50-56 s).
``--quick``: a small simulated Bouc-Wen config (300 rows, noise, band and novelty calibrated) and a 1 s sweep.

    python bench/bench_update.py [--quick] [--record PATH --window START:END]
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common as C

QUICK_CONFIG = """
name = "bw-update"
[system]
fs = 750.0
units = { u = "N", y = "m" }
output = "displacement"
[physics]
mass = 2.0
[model]
ny = 4
nu = 4
max_train_points = 300
restarts = 0
noise_calibration = "lags"
band_calibration = "lags"
[predict]
mc_paths = 32
method = "linear"
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 1 }
[[records]]
name = "lag-sweep"
roles = ["lags", "verify"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }
[[records]]
name = "h1"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 2 }
[[records]]
name = "h2"
roles = ["healthy"]
simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 0.5, f0 = 20.0, f1 = 60.0 }
noise = { fraction = 0.01, seed = 3 }
"""


def extra(ap):
    ap.add_argument("--record", default=None, help="the new record (default: the 19 Hz sine of the lab data)")
    ap.add_argument("--window", default=None, help="its window START:END [s] (default 24:40, 16 s)")


def gpnarx(*argv) -> tuple[float, dict]:
    """Wall time [s] of one ``gpnarx`` process and its --json answer."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gpnarx", *argv, "--json"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"gpnarx {' '.join(argv)} exited {proc.returncode}:\n{proc.stderr[-2000:]}")
    return wall, json.loads(proc.stdout)


def main():
    args = C.parse_args(__doc__, extra)
    if args.threads is not None:
        os.environ["GPNARX_BLAS_THREADS"] = str(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        reg = tmp / "registry"
        if args.quick:
            config = tmp / "bw-update.toml"
            config.write_text(QUICK_CONFIG)
            record = tmp / "new.npz"
            subprocess.run([sys.executable, "-m", "gpnarx", "simulate", "bouc-wen", "--excitation", "sweep",
                            "--amplitude", "35", "--f0", "20", "--f1", "60", "--duration", "1", "--seed", "5",
                            "--out", str(record)], check=True, capture_output=True)
            name, window, model = "bw-update", args.window, "bw-update"
            train_argv = [str(config), "--registry", str(reg), "--no-report"]
            update_argv = ["update", name, str(record), "--registry", str(reg), "--config", str(config)]
        else:
            from gpnarx.training.datapaths import BERT_DATA_ENV, bert_data_dir

            data = bert_data_dir()
            os.environ[BERT_DATA_ENV] = str(data)
            record = Path(args.record) if args.record else data / "Sine" / "Sine_19Hz"
            name, window, model = "bert-real", args.window or "24:40", "bert-real"
            train_argv = [name, "--registry", str(reg)]
            update_argv = ["update", name, str(record), "--registry", str(reg)]
        if window:
            update_argv += ["--window", window]
        train_s, trained = gpnarx("train", *train_argv)
        update_s, updated = gpnarx(*update_argv)
    steps = updated["seconds"]
    rows = updated["rows"]
    C.result(bench="update", model=model, record=Path(record).name, window=window or "whole",
             update_s=update_s, baseline=train_s,
             baseline_what="gpnarx_train_of_the_same_model_same_run(ML-II,calibrations,evaluation,report)",
             ratio=update_s / train_s, target_ratio=0.1,
             rank_update_s=steps.get("rank_update", 0.0), noise_s=steps.get("noise", 0.0),
             band_s=steps.get("band", 0.0), novelty_s=steps.get("novelty", 0.0), judge_s=steps.get("judge", 0.0),
             rows_added=rows["rows_added"], rows_dropped=rows["rows_dropped"], rows=rows["rows"],
             versions=f"{trained['version']}->{updated['version']}", load=C.load())


if __name__ == "__main__":
    main()
