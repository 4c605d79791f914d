"""Lag surface of section 2.2 (step 2): free-run fit % (eq. 14) for each (ny, nu).

For every cell the GP-NARX is trained (ML-II) on the config's ``train`` records and its free-run
mean on the ``lags`` records is scored with eq. (14) (a config with several channels: each record by its
worst output channel, ``mimo_pipeline.mimo_lag_cell``, the channels' fits in the cell's ``channel_fits``).
Cells run in parallel with joblib on local cores, or on an existing Dask cluster (``scheduler``: an address or a
``distributed.Client``), where the config and the record arrays are sent to the workers (:func:`lag_cell_data`),
not read from a path.
Finished cells are cached on disk (one JSON file per cell, keyed by the config content and the
settings), so an interrupted surface resumes where it stopped.

The choice rule and the grid-edge check are :mod:`gpnarx.training.lagchoice` (re-exported here):
``lag_surface`` returns the chosen cell and, in ``edge``, the lag axes on which the best cell is at
the largest value tried (for example ``["nu"]``) so the caller can warn and the user can extend the
range; the choice itself is not changed.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from gpnarx.storage.atomicio import write_atomic
from gpnarx.training.config import load_config
from gpnarx.training.free_run_fits import free_run_fits
from gpnarx.training.lagchoice import DEFAULT_TOLERANCE, choose_lags, edge_message, grid_edge
from gpnarx.training.mimo_pipeline import mimo_lag_cell
from gpnarx.training.prepare import model_from_config, shorten

__all__ = ["DEFAULT_TOLERANCE", "cell_data", "choose_lags", "edge_message", "grid_edge", "lag_cell", "lag_cell_data",
           "lag_surface", "write_surface"]


@lru_cache(maxsize=4)
def _load(config_path: str, mtime: float):
    cfg = load_config(config_path)
    return cfg, cfg.records_for("train"), cfg.records_for("lags")


def lag_cell(config_path: str, ny: int, nu: int, settings: dict) -> dict:
    """Train at (ny, nu) and score free-run fit % on the ``lags`` records: ``fit`` is the mean of their
    fits, ``fits`` holds each record's fit by name.

    The free-run mean comes from the first-order propagation (deterministic); it equals feeding
    back the mean, as eq. (14) scores the model mean output.
    """
    cfg, train, lag_recs = _load(str(config_path), os.path.getmtime(config_path))
    return lag_cell_data(cell_data(cfg, train, lag_recs, settings), ny, nu, settings)


def cell_data(cfg, train: list, lag_recs: list, settings: dict) -> tuple:
    """What every cell needs: the config and the (quick-mode shortened) ``train`` and ``lags`` records."""
    if settings.get("max_seconds"):  # quick mode: the first max_seconds of every record
        train = [shorten(r, settings["max_seconds"]) for r in train]
        lag_recs = [shorten(r, settings["max_seconds"]) for r in lag_recs]
    if not lag_recs:
        raise ValueError(f"{cfg.path}: no record has role 'lags'")
    return cfg, train, lag_recs


def lag_cell_data(data: tuple, ny: int, nu: int, settings: dict) -> dict:
    """:func:`lag_cell` on data already in memory (``cell_data``): the task a Dask worker runs, with the
    config and the record arrays sent to it rather than read from a path."""
    cfg, train, lag_recs = data
    if cfg.several_channels:  # a model with several channels: each record scored by its worst channel
        return mimo_lag_cell(cfg, train, lag_recs, ny, nu, settings)
    t0 = time.perf_counter()
    try:
        model = model_from_config(cfg, ny, nu, **settings).fit(train)
        fits = free_run_fits(model, lag_recs, score_clean=bool(settings.get("score_clean")))
        fit = float(np.mean(list(fits.values())))
        err = None
    except (ValueError, np.linalg.LinAlgError) as exc:
        fit, fits, err = float("nan"), {}, str(exc)
    return {"ny": int(ny), "nu": int(nu), "fit": fit, "fits": fits, "seconds": time.perf_counter() - t0,
            "error": err}


def _cache_key(config_path: Path, settings: dict) -> str:
    h = hashlib.sha256(Path(config_path).read_bytes())
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:16]


def lag_surface(config_path, ny_values, nu_values, *, jobs: int = -1, scheduler=None,
                cache_dir=None, settings: dict | None = None, progress: bool = False,
                tolerance: float = DEFAULT_TOLERANCE) -> dict:
    """Compute the surface; returns {"cells": [...], "chosen": {...}, "best": {...}, "edge": [...], ...}
    (``edge``: the axes on which the best cell is at the grid's largest value, see module docstring)."""
    config_path = Path(config_path).resolve()
    settings = dict(settings or {})
    cache_dir = Path(cache_dir) if cache_dir else config_path.parent / ".lagcache"
    key = _cache_key(config_path, settings)
    cdir = cache_dir / key
    cdir.mkdir(parents=True, exist_ok=True)
    grid = [(int(a), int(b)) for a in ny_values for b in nu_values]
    cells, todo = {}, []
    for ny, nu in grid:
        f = cdir / f"ny{ny}_nu{nu}.json"
        if f.is_file():
            try:
                cells[(ny, nu)] = json.loads(f.read_text())
                continue
            except json.JSONDecodeError:
                pass
        todo.append((ny, nu))
    bar = None
    if progress and todo:
        from gpnarx._progress import progress_bar

        bar = progress_bar(total=len(grid), initial=len(grid) - len(todo), desc="lag surface", unit="cell",
                           lines=True)  # minutes per cell: a line per cell even without tqdm

    def store(res):
        write_atomic(cdir / f"ny{res['ny']}_nu{res['nu']}.json", json.dumps(res, allow_nan=True))
        cells[(res["ny"], res["nu"])] = res
        if bar is not None:
            bar.update(1)

    t0 = time.perf_counter()
    if todo:
        if scheduler not in (None, ""):
            # on a Dask cluster the config and the record arrays are loaded here and sent to the
            # workers once, so no worker reads the config or a record file from a path
            from gpnarx.training.distributed import TaskRunner

            cfg = load_config(config_path)
            data = cell_data(cfg, cfg.records_for("train"), cfg.records_for("lags"), settings)
            with TaskRunner(scheduler) as runner:
                shared = runner.share(data)
                for _, res, exc in runner.imap(lag_cell_data, [(shared, ny, nu, settings) for ny, nu in todo]):
                    if exc is not None:
                        raise exc
                    store(res)
        else:
            for res in Parallel(n_jobs=jobs, return_as="generator")(
                    delayed(lag_cell)(str(config_path), ny, nu, settings) for ny, nu in todo):
                store(res)
    if bar is not None:
        bar.close()
    ordered = [cells[g] for g in grid]
    chosen = choose_lags(ordered, tolerance)
    best = max((c for c in ordered if np.isfinite(c["fit"])), key=lambda c: c["fit"])
    return {"config": str(config_path), "ny": list(ny_values), "nu": list(nu_values), "cells": ordered,
            "chosen": chosen, "best": best, "edge": grid_edge(best, ny_values, nu_values),
            "tolerance": tolerance, "settings": settings,
            "seconds": time.perf_counter() - t0, "cached_cells": len(grid) - len(todo)}


#: why ``write_surface`` draws no heat map, and how to get one
FIGURE_SKIPPED = "matplotlib is not installed (pip install 'gpnarx[train]'; the surface file is written)"


def write_surface(surface: dict, out) -> list[Path]:
    """Write the surface as JSON (or CSV when ``out`` ends in .csv) plus a heat-map PNG beside it; without
    matplotlib no PNG, and ``surface["figure_skipped"]`` says why (``FIGURE_SKIPPED``)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    paths = []
    if out.suffix.lower() == ".csv":
        lines = ["ny,nu,fit,seconds"] + [f"{c['ny']},{c['nu']},{c['fit']},{c['seconds']:.3f}" for c in surface["cells"]]
        write_atomic(out, "\n".join(lines) + "\n")
    else:
        clean = json.loads(json.dumps(surface, default=float).replace("NaN", "null"))
        write_atomic(out, json.dumps(clean, indent=1))
    paths.append(out)
    try:
        # the report module imports matplotlib and selects its Agg backend: imported only here, when a
        # figure is drawn, not in every lag-surface worker process that imports this module
        from gpnarx.training.report_figures import lag_surface_figure

        png = out.with_suffix(".png")
        lag_surface_figure(surface["cells"], (surface["chosen"]["ny"], surface["chosen"]["nu"]),
                           surface.get("paper"), png)
        paths.append(png)
    except ImportError:
        surface["figure_skipped"] = f"{out.with_suffix('.png').name} not written: {FIGURE_SKIPPED}"
    return paths
