"""``gpnarx update NAME[:VERSION] RECORD... [--registry R] [--config CONFIG] [--accept-novel]``.

Writes a new version of a model conditioned also on new healthy records, hyperparameters held (a rank update of
the exact posterior's factor), with its noise, band and novelty threshold recalibrated and its lineage in the
manifest (``gpnarx.training.update``). CLI only, like ``gpnarx calibrate``: the service never writes its registry,
and serves the new version as it serves any new version.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import sys

from gpnarx.cli.cmd_predict import add_fs_argument
from gpnarx.cli.errors import CLIError, UsageError


def add_parser(sub):
    p = sub.add_parser("update", help="new bundle version conditioned also on new healthy records (hyperparameters "
                                      "held; noise, band and novelty threshold recalibrated)")
    p.add_argument("model", metavar="NAME", help="NAME or NAME:VERSION to update (latest version when omitted)")
    p.add_argument("records", nargs="+", metavar="RECORD",
                   help="new healthy records (.npz, .npy, .csv, .mat or LMS Test.Lab folders) with measured y, at the "
                        "model's fs")
    p.add_argument("--registry", default=None,
                   help="registry folder or URL (default: $GPNARX_REGISTRY or the default registry)")
    p.add_argument("--config", default=None,
                   help="the dataset config the model was trained from (a TOML file or a shipped config's name; "
                        "default: the shipped config named like the model): its held-out 'lags' records recalibrate "
                        "the noise and band, its 'healthy' records the novelty threshold")
    p.add_argument("--accept-novel", action="store_true", dest="accept_novel",
                   help="take records the model's novelty monitor judges novel (refused by default: updating on "
                        "damage teaches the monitor to accept it); the new version's lineage says so")
    p.add_argument("--window", default=None, metavar="START:END",
                   help="use only this time window of every record [s]")
    p.add_argument("--version", default=None, help="version to write (default: next free)")
    add_fs_argument(p)
    p.set_defaults(func=run)


def _config_for(arg: str | None, model_name: str):
    """The config path: ``--config`` as ``gpnarx train`` resolves it, else the shipped config named like the model,
    else None (the update then runs without recalibration where the model has none)."""
    from gpnarx.cli.cmd_train import resolve_config
    from gpnarx.configs import shipped_config, shipped_config_names

    if arg:
        return resolve_config(arg)
    return shipped_config(model_name) if model_name in shipped_config_names() else None


def run(args):
    from gpnarx.cli.cmd_predict import check_fs, open_model, parse_window, read_cli_record, resolve_registry
    from gpnarx.storage.bundle import BundleError
    from gpnarx.storage.registry import parse_model_ref
    from gpnarx.training.config import ConfigError, load_config
    from gpnarx.training.update import UpdateError, update

    if args.version is not None:
        try:
            from gpnarx.storage.bundle import check_version

            check_version(args.version)
        except BundleError as exc:
            raise UsageError(f"--version: {exc}") from None
    window = parse_window(args.window) if args.window else None
    # BLAS as gpnarx train leaves it (the library's threads for the held-out noise calibration's products; the
    # estimator limits BLAS itself around each free run, runtime.free_run_blas), not calibrate's one thread
    try:
        name, version = parse_model_ref(args.model)
    except BundleError as exc:
        raise UsageError(f"NAME: {exc}") from None
    root = resolve_registry(args.registry, name)
    bundle = open_model(root, name, version)
    cfg_path = _config_for(args.config, name)
    try:
        cfg = None if cfg_path is None else load_config(cfg_path)
    except (ConfigError, OSError) as exc:
        raise CLIError(f"--config: {exc}") from None
    recs = []
    for r in args.records:
        rec = read_cli_record(r, args.fs)
        if window:
            rec = rec.window(*window)
        if rec.y is None:
            raise CLIError(f"{r}: an update record needs its measured output y")
        rec = check_fs(rec, bundle, str(r))
        rec.name = str(r) + (f" [{window[0]:g}:{window[1]:g} s]" if window else "")  # the path given
        recs.append(rec)
    log = (lambda m: None) if args.json else (lambda m: print(m, file=sys.stderr))
    log(f"updating {bundle.name}:{bundle.version} with {len(recs)} record(s)"
        + (f", recalibrating with {cfg.path}" if cfg is not None else ""))
    try:
        res = update(bundle, recs, root, config=cfg, accept_novel=args.accept_novel, version=args.version, log=log)
    except UpdateError as exc:
        raise CLIError(str(exc)) from None
    lin = res["lineage"]
    return {"name": res["name"], "version": res["version"], "path": res["path"],
            "parent_version": res["parent_version"], "accept_novel": lin["accept_novel"], "records": lin["records"],
            "rows": lin["rows"], "recalibrated": lin["recalibrated"], "updated": lin["updated"],
            "seconds": res["seconds"]}
