"""``gpnarx train CONFIG.toml --registry DIR [--name N] [--version V]``."""
from __future__ import annotations

import sys


def add_parser(sub):
    p = sub.add_parser("train", help="train a bundle from a dataset config and write it with its report")
    p.add_argument("config", help="dataset config (TOML)")
    p.add_argument("--registry", required=True, help="registry folder (bundles go to REGISTRY/NAME/VERSION)")
    p.add_argument("--name", default=None, help="bundle name (default: the config's name)")
    p.add_argument("--version", default=None, help="version (positive integer; default: next free)")
    p.add_argument("--mc", type=int, default=None, help="Monte Carlo paths for verification (default: config)")
    p.add_argument("--ny", type=int, default=None, help="override the config's output lags")
    p.add_argument("--nu", type=int, default=None, help="override the config's input lags")
    p.add_argument("--no-report", action="store_true", help="skip the HTML/PNG report")
    p.set_defaults(func=run)


def run(args):
    from gpnarx.training.pipeline import train

    quiet = args.json
    res = train(args.config, args.registry, name=args.name, version=args.version, progress=not quiet,
                mc_paths=args.mc, ny=args.ny, nu=args.nu, report=not args.no_report,
                log=None if quiet else (lambda m: print(m, file=sys.stderr)))
    return {"name": res["name"], "version": res["version"], "path": res["path"], "metrics": res["metrics"]}
