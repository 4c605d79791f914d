"""``gpnarx train CONFIG.toml|NAME --registry DIR [--name N] [--version V] [--choose-lags] [--scheduler ADDRESS]``.

``NAME`` is a shipped config (``gpnarx.configs``, e.g. ``bouc-wen``), found from any working folder; an
existing file of that name wins. ``--choose-lags`` computes the lag surface over the config's
``[lags]`` ranges first and trains at the chosen cell (the surface goes into the report).
``--scheduler``: the lag surface, the verification/validation free runs and the report's figures
run as tasks on that Dask cluster, with the config and record arrays sent to the workers; the
bundle's metrics are those of the local run.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import importlib.util
import sys
from contextlib import ExitStack
from pathlib import Path

from gpnarx.cli.errors import CLIError, UsageError
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
    p.add_argument("--mode", choices=("exact", "sparse"), default=None,
                   help="override the config's [model] mode: 'exact' is the full GP on the selected rows (on the real "
                        "rig the more faithful free run, docs/results-accelerator.md; its predictions cost O(N^2) a "
                        "step), 'sparse' the inducing-point one")
    p.add_argument("--train-points", type=int, default=None, metavar="N",
                   help="override the config's [model] max_train_points (the rows ML-II, and in exact mode the "
                        "posterior, use)")
    p.add_argument("--backend", choices=("numpy", "jax"), default=None,
                   help="where ML-II and the exact posterior's solves run (default: the config's [model] "
                        "fit_backend, else numpy); 'jax' on a GPU makes exact mode at 10-20 thousand rows practical "
                        "(docs/accelerator.md)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML/PNG report")
    p.add_argument("--choose-lags", action="store_true",
                   help="compute the lag surface over the config's [lags] ny/nu ranges first and train at the chosen "
                        "cell (instead of [model] ny/nu); cells are cached in --lag-cache")
    p.add_argument("--lag-cache", default=None,
                   help="cache of finished lag-surface cells (default: CONFIG_DIR/.lagcache, as 'gpnarx lags')")
    p.add_argument("--jobs", type=int, default=-1, help="local parallel jobs for the lag surface (-1 = all cores)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask scheduler, e.g. tcp://host:8786: lag surface, free runs and report figures "
                        "run as tasks on its workers (needs the 'dask' extra); default: this machine")
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

    if args.scheduler is not None and not args.scheduler.strip():
        raise UsageError("--scheduler must be a Dask scheduler address such as tcp://host:8786")
    if args.scheduler and importlib.util.find_spec("distributed") is None:
        raise CLIError("--scheduler needs dask.distributed: pip install 'gpnarx[dask]'")
    config = resolve_config(args.config)
    if not args.no_report:  # fail before the training, not after it
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise CLIError("the training report's figures need matplotlib: pip install 'gpnarx[train]' "
                           "(or give --no-report)") from None
    quiet = args.json
    log = None if quiet else (lambda m: print(m, file=sys.stderr))
    with ExitStack() as stack:
        scheduler = None
        if args.scheduler:
            from gpnarx.training.distributed import TaskRunner

            # one client for the lag surface and the training's tasks
            scheduler = stack.enter_context(TaskRunner(args.scheduler)).client
        surface, ny, nu = None, args.ny, args.nu
        if args.choose_lags:
            surface = _choose_lags(args, config, scheduler, quiet)
            ch = surface["chosen"]
            ny, nu = ch["ny"], ch["nu"]
            if log:
                log(f"lag surface: chosen ny={ny} nu={nu} (fit {ch['fit']:.2f} %) from {len(surface['cells'])} cells")
        res = train(config, args.registry, name=args.name, version=args.version, progress=not quiet,
                    mc_paths=args.mc, ny=ny, nu=nu, report=not args.no_report, lag_surface=surface, log=log,
                    scheduler=scheduler, model_overrides=_model_overrides(args))
    out = {"name": res["name"], "version": res["version"], "path": res["path"], "metrics": res["metrics"]}
    if surface is not None:
        out["lags"] = {"ny": ny, "nu": nu, "fit": surface["chosen"]["fit"], "cells": len(surface["cells"]),
                       "cached_cells": surface["cached_cells"]}
    if not args.json:  # a readable summary; --json gives the whole answer as one object
        print(summary(out, _units(out["path"])))
        return None
    return out


def _units(path) -> dict:
    """The written bundle's units (its manifest), {} when it cannot be read (a remote registry)."""
    import json

    try:
        return json.loads((Path(path) / "manifest.json").read_text()).get("units") or {}
    except (OSError, ValueError):
        return {}


def _num(v) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return "-" if v is None else str(v)
    if isinstance(v, int):
        return str(v)
    a = abs(v)
    return f"{v:.3e}" if a and (a < 1e-3 or a >= 1e5) else f"{v:.4g}"


# the per-record columns of the summary: key, header, unit ("y": the output's unit)
_COLUMNS = (("role", "role", ""), ("use", "use", ""), ("fit", "fit", "%"), ("rmse", "RMSE", "y"),
            ("coverage", "coverage", "%"), ("band_width", "band width", "y"), ("n_samples", "samples", ""),
            ("novelty_score", "novelty score", ""), ("verdict", "verdict", ""))


def summary(out: dict, units: dict | None = None) -> str:
    """``gpnarx train``'s answer as text: the bundle written, the run's figures with units, and a table
    of the per-record metrics (fit, RMSE and band width in the output's unit, coverage)."""
    m = out.get("metrics") or {}
    yu = (units or {}).get("y") or "-"
    lines = [f"bundle {out['name']} version {out['version']} written to {out['path']}"]
    run = []
    if m.get("fit_seconds") is not None:
        run.append(f"fit {_num(m['fit_seconds'])} s")
    if m.get("n_train") is not None:
        run.append(f"{m['n_train']} training points" + (f" of {m['n_rows']} rows" if m.get("n_rows") else ""))
    if m.get("nlml") is not None:
        run.append(f"NLML {_num(m['nlml'])}")
    if m.get("mc_paths") is not None:
        run.append(f"{m['mc_paths']} Monte Carlo paths ({m.get('method', 'mc')})")
    if run:
        lines.append(", ".join(run))
    if out.get("lags"):
        lg = out["lags"]
        lines.append(f"lags chosen: ny={lg['ny']} nu={lg['nu']} (fit {_num(lg['fit'])} %, {lg['cells']} cells)")
    recs = m.get("records") or {}
    if any(isinstance(r, dict) and isinstance(r.get("channels"), dict) for r in recs.values()):
        # a model with several channels (training.mimo_pipeline): one row per record and output channel
        recs = {f"{name} {ch}": {"role": r.get("role"), **mm}
                for name, r in recs.items() if isinstance(r, dict)
                for ch, mm in (r.get("channels") or {"-": {}}).items()}
    if recs:
        cols = [c for c in _COLUMNS if any(isinstance(r, dict) and r.get(c[0]) is not None for r in recs.values())]
        head = ["record"] + [f"{h} [{yu if u == 'y' else u}]" if u else h for _, h, u in cols]
        rows = [[name] + [_num(r.get(k)) if isinstance(r, dict) else "-" for k, _, _ in cols]
                for name, r in recs.items()]
        widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
        lines.append("")
        for row in [head, *rows]:
            lines.append("  ".join(str(x).ljust(w) for x, w in zip(row, widths)).rstrip())
    report = Path(str(out["path"])) / "report" / "report.html"
    if report.is_file():
        lines.append(f"report: {report}")
    lines.append("(--json prints every metric as one JSON object)")
    return "\n".join(lines)


def _model_overrides(args) -> dict | None:
    """The [model] settings the command line overrides (None: the config's own)."""
    if args.train_points is not None and args.train_points < 2:
        raise UsageError(f"--train-points must be at least 2, got {args.train_points}")
    over = {"fit_backend": args.backend, "mode": args.mode, "max_train_points": args.train_points}
    over = {k: v for k, v in over.items() if v is not None}
    return over or None


def _choose_lags(args, config, scheduler, quiet) -> dict:
    from gpnarx.training.config import load_config, parse_range
    from gpnarx.training.lags import edge_message, lag_surface

    if args.ny is not None or args.nu is not None:
        raise UsageError("--choose-lags picks ny and nu itself: drop --ny/--nu (the ranges are the config's [lags])")
    cfg = load_config(config)
    ranges = []
    for axis in ("ny", "nu"):
        spec = cfg.lags.get(axis)
        if spec is None:
            raise CLIError(f"{config}: --choose-lags needs [lags] {axis} (a range LO:HI[:STEP]) in the config")
        try:
            ranges.append(parse_range(spec))
        except ValueError as exc:
            raise CLIError(f"{config}: [lags] {axis}: {exc}") from None
    if not cfg.names_for("lags"):
        raise CLIError(f"{config}: --choose-lags needs records with role 'lags'")
    surface = lag_surface(config, ranges[0], ranges[1], jobs=args.jobs, scheduler=scheduler, cache_dir=args.lag_cache,
                          progress=not quiet)
    if surface["edge"] and not quiet:
        print(f"gpnarx train: warning: {edge_message(surface)}", file=sys.stderr)
    return surface
