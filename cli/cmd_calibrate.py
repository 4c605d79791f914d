"""``gpnarx calibrate --model NAME[:VERSION] RECORD... [--registry R] [--false-alarm-rate F]``.

Writes a new version of the bundle whose novelty threshold, calibration envelope and probe contract
come from the given healthy records; the GP is not refitted (its arrays are copied byte for byte).
CLI only: the service never writes its registry (see ``gpnarx.training.novelty_calibration``).

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import sys

from gpnarx.cli.cmd_predict import add_fs_argument
from gpnarx.cli.errors import CLIError, UsageError


def add_parser(sub):
    p = sub.add_parser("calibrate", help="new bundle version with a novelty threshold and probe contract from "
                                         "healthy records (no refit)")
    p.add_argument("--registry", default=None,
                   help="registry folder (default: $GPNARX_REGISTRY or the default registry, built on first use)")
    p.add_argument("--model", required=True, help="NAME or NAME:VERSION to calibrate (latest version when omitted)")
    p.add_argument("records", nargs="+", metavar="RECORD",
                   help="healthy records (.npz, .npy, .csv, .mat or LMS Test.Lab folders) with measured y, taken "
                        "with the probe excitation the monitor will be used with; at least 2")
    p.add_argument("--false-alarm-rate", type=float, default=0.01, dest="false_alarm_rate",
                   help="target false-alarm rate of the threshold (default 0.01)")
    p.add_argument("--mc", type=int, default=None,
                   help="Monte Carlo paths per record (default: the model's for novelty, as 'gpnarx novelty' and the "
                        "HTTP service use)")
    add_fs_argument(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the first record's paths (record k: seed + k)")
    p.add_argument("--method", choices=("mc", "linear"), default="mc", help="uncertainty propagation")
    p.add_argument("--score-method", choices=("rms_standardised_residual", "segment_median_rms"), default=None,
                   help="novelty score (default: the bundle's, else rms_standardised_residual)")
    p.add_argument("--window", default=None, metavar="START:END",
                   help="use only this time window of every record [s] (e.g. a steady part of an LMS run)")
    p.add_argument("--version", default=None, help="version to write (default: next free)")
    p.set_defaults(func=run)


def run(args):
    from gpnarx.cli.cmd_predict import check_fs, mc_paths, open_model, parse_window, read_cli_record, resolve_registry
    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.bundle import BundleError
    from gpnarx.storage.registry import parse_model_ref
    from gpnarx.training.novelty_calibration import calibrate

    if not 0.0 < args.false_alarm_rate < 0.5:
        raise UsageError(f"--false-alarm-rate must be in (0, 0.5), got {args.false_alarm_rate}")
    if args.mc is not None:
        mc_paths(args.mc)
    if len(args.records) < 2:
        raise UsageError(f"at least 2 healthy records are needed, got {len(args.records)}")
    tune_for_free_run(None)
    try:
        name, version = parse_model_ref(args.model)
    except BundleError as exc:
        raise CLIError(str(exc)) from None
    root = resolve_registry(args.registry)  # a folder or an fsspec URL: the new version is written there
    bundle = open_model(root, name, version)
    n_paths = mc_paths(args.mc, bundle, "novelty")
    window = parse_window(args.window) if args.window else None
    recs = []
    for r in args.records:
        rec = read_cli_record(r, args.fs)
        if window:
            rec = rec.window(*window)
        if rec.y is None:
            raise CLIError(f"{r}: a healthy record needs its measured output y")
        rec = check_fs(rec, bundle, str(r))
        rec.name = str(r)  # calibration records are named by the path given
        recs.append(rec)
    log = (lambda m: None) if args.json else (lambda m: print(m, file=sys.stderr))
    log(f"calibrating {bundle.name}:{bundle.version} on {len(recs)} healthy record(s)")
    res = calibrate(bundle, recs, root, false_alarm_rate=args.false_alarm_rate, score_method=args.score_method,
                    n_paths=n_paths, seed=args.seed, propagation=args.method, version=args.version)
    nov = res["novelty"]
    log(f"threshold {nov['threshold']:.4g} (false-alarm rate {nov['false_alarm_rate']}); probe {nov['probe']['kind']}"
        + (f" {nov['probe']['frequency']:.4g} Hz" if nov["probe"]["frequency"] else "")
        + f"; written {res['name']}:{res['version']} at {res['path']}")
    return {"name": res["name"], "version": res["version"], "path": res["path"],
            "source_version": res["source_version"], "threshold": nov["threshold"],
            "false_alarm_rate": nov["false_alarm_rate"], "n_healthy": nov["n_healthy"], "score_method": nov["method"],
            "probe": nov["probe"], "envelope": nov["envelope"], "records": res["records"]}
