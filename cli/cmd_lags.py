"""``gpnarx lags CONFIG.toml --ny LO:HI --nu LO:HI [--jobs N] [--scheduler ADDRESS] --out FILE``.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import importlib.util
import sys

from gpnarx.cli.errors import CLIError, UsageError


def add_parser(sub):
    p = sub.add_parser("lags", help="compute the lag surface (fit %% per ny, nu) on the config's 'lags' records")
    p.add_argument("config", help="dataset config (TOML)")
    p.add_argument("--ny", default=None, help="output-lag range LO:HI[:STEP] (default: the config's [lags] ny)")
    p.add_argument("--nu", default=None, help="input-lag range LO:HI[:STEP] (default: the config's [lags] nu)")
    p.add_argument("--jobs", type=int, default=-1, help="local parallel jobs (joblib; -1 = all cores)")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler, e.g. tcp://host:8786 "
                                                       "(needs the 'dask' extra)")
    p.add_argument("--max-train-points", type=int, default=None, help="training-point cap per cell (default: config)")
    p.add_argument("--tolerance", type=float, default=0.5, help="choice rule: fit within this many points of the best")
    p.add_argument("--cache-dir", default=None, help="cache of finished cells (default: CONFIG_DIR/.lagcache)")
    p.add_argument("--out", required=True, help="output file (.json or .csv); a heat-map .png is written beside it")
    p.set_defaults(func=run)


def run(args):
    # start-up: imported when the command runs (see gpnarx.cli)
    from gpnarx.training.config import load_config, parse_range
    from gpnarx.training.lags import edge_message, lag_surface, write_surface

    if args.scheduler and importlib.util.find_spec("distributed") is None:
        raise CLIError("--scheduler needs dask.distributed: pip install 'gpnarx[dask]'")
    cfg = load_config(args.config)
    ny_spec = args.ny or cfg.lags.get("ny")
    nu_spec = args.nu or cfg.lags.get("nu")
    if ny_spec is None or nu_spec is None:
        raise UsageError("give --ny and --nu ranges (or [lags] ny/nu in the config)")
    try:
        ny_values = parse_range(ny_spec)
    except ValueError as exc:
        raise UsageError(f"--ny: {exc}") from None
    try:
        nu_values = parse_range(nu_spec)
    except ValueError as exc:
        raise UsageError(f"--nu: {exc}") from None
    if not cfg.names_for("lags"):
        raise CLIError(f"{args.config}: no record has role 'lags'")
    settings = {}
    if args.max_train_points:
        settings["max_train_points"] = args.max_train_points
    surface = lag_surface(args.config, ny_values, nu_values, jobs=args.jobs, scheduler=args.scheduler,
                          cache_dir=args.cache_dir, settings=settings, progress=not args.json,
                          tolerance=args.tolerance)
    paths = write_surface(surface, args.out)
    ch = surface["chosen"]
    if surface["edge"]:
        print(f"gpnarx lags: warning: {edge_message(surface)}", file=sys.stderr)
    if surface.get("figure_skipped"):
        print(f"gpnarx lags: note: {surface['figure_skipped']}", file=sys.stderr)
    return {"chosen": {"ny": ch["ny"], "nu": ch["nu"], "fit": ch["fit"]},
            "best": {"ny": surface["best"]["ny"], "nu": surface["best"]["nu"], "fit": surface["best"]["fit"]},
            "edge": surface["edge"], "cells": len(surface["cells"]), "cached_cells": surface["cached_cells"],
            "seconds": surface["seconds"], "files": [str(p) for p in paths],
            "figure_skipped": surface.get("figure_skipped")}
