"""``gpnarx train CONFIG.toml|NAME --registry DIR [--name N] [--version V]``.

``NAME`` is a shipped config (``gpnarx.configs``, e.g. ``bouc-wen``), found from any working folder; an
existing file of that name wins.
"""
from __future__ import annotations

import sys
from pathlib import Path

from gpnarx.cli.errors import CLIError
from gpnarx.configs import shipped_config, shipped_config_names


def add_parser(sub):
    p = sub.add_parser("train", help="train a bundle from a dataset config and write it with its report")
    p.add_argument("config", help="dataset config (TOML file) or the name of a shipped config "
                                  f"({', '.join(shipped_config_names())})")
    p.add_argument("--registry", required=True, help="registry folder (bundles go to REGISTRY/NAME/VERSION)")
    p.add_argument("--name", default=None, help="bundle name (default: the config's name)")
    p.add_argument("--version", default=None, help="version (positive integer; default: next free)")
    p.add_argument("--mc", type=int, default=None, help="Monte Carlo paths for verification (default: config)")
    p.add_argument("--ny", type=int, default=None, help="override the config's output lags")
    p.add_argument("--nu", type=int, default=None, help="override the config's input lags")
    p.add_argument("--no-report", action="store_true", help="skip the HTML/PNG report")
    p.set_defaults(func=run)


def resolve_config(arg: str):
    """A config path: ``arg`` itself when it exists or looks like a file path, else the shipped config so named."""
    p = Path(arg).expanduser()
    if p.exists() or p.suffix or len(p.parts) > 1:
        return p
    if arg in shipped_config_names():
        return shipped_config(arg)
    raise CLIError(f"no config file {arg!r} and no shipped config of that name "
                   f"(shipped: {', '.join(shipped_config_names())})")


def run(args):
    # start-up: imported when the command runs, not when the parser is built (the pipeline pulls in
    # scipy and scikit-learn: half a second for every gpnarx command; see gpnarx.cli)
    from gpnarx.training.pipeline import train

    config = resolve_config(args.config)
    quiet = args.json
    res = train(config, args.registry, name=args.name, version=args.version, progress=not quiet,
                mc_paths=args.mc, ny=args.ny, nu=args.nu, report=not args.no_report,
                log=None if quiet else (lambda m: print(m, file=sys.stderr)))
    return {"name": res["name"], "version": res["version"], "path": res["path"], "metrics": res["metrics"]}
