"""How much of the noise run to train on, and which posterior: the real rig's training data against its classes.

``bert-real`` trains on the first 7 s of the 0.25 V noise run and keeps the rest (7-16 s, from its measured
outputs) among its 'lags' records. The drive of that run stops at about 8 s, so the split decides how much of
the driven noise the GP sees. For each planned cell (split in s, posterior mode, ML-II rows N, inducing points
M): the config with the noise run split there, ML-II and the noise calibration on ``fit_backend``, then the
linearised free run of every 'lags' record (the choice is made by the worst of them) and of every 'validate'
record (reported, never used to choose): fit (eq. 14, %), the coverage of eq. 8-9's band (no discrepancy
term) and its mean half-width over the record's standard deviation.

    python -m studies.split_study CONFIG --out DIR [--plan 7:exact:1500:0,7:sparse:1500:256]
        [--fit-backend jax] [--sim-backend jax]

Writes DIR/split_study.json after every cell (a run cut short keeps what it measured).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gpnarx.model.metrics import fit_percent
from gpnarx.training.config import load_config
from gpnarx.training.prepare import model_from_config

SHIPPED_SPLIT = 7.0  # s: the shipped config's noise-run split (train 0-7 s, 'lags' 7-16 s)
DEFAULT_PLAN = "5:sparse:1500:512,7:exact:1500:0,7:sparse:1500:256,7:exact:3000:0,11:exact:1500:0,11:sparse:1500:256"


def parse_plan(text: str) -> list[tuple[float, str, int, int]]:
    """'split:mode:N:M,...' as (split s, mode, ML-II rows, inducing points; 0 for exact) cells."""
    cells = []
    for item in text.split(","):
        parts = item.strip().split(":")
        if len(parts) != 4 or parts[1] not in ("exact", "sparse"):
            raise ValueError(f"plan cell {item!r}: expected split:exact|sparse:N:M, e.g. 7:exact:1500:0")
        cells.append((float(parts[0]), parts[1], int(parts[2]), int(parts[3])))
    return cells


def split_config_text(text: str, split: float) -> str:
    """The shipped config's text with the noise run split at ``split`` s (train before, 'lags' after)."""
    train_w, lags_w = f"window = [0.0, {SHIPPED_SPLIT}]", f"window = [{SHIPPED_SPLIT}, 16.0]"
    if text.count(train_w) != 1 or text.count(lags_w) != 1:
        raise ValueError(f"the config does not split its noise run at the shipped {SHIPPED_SPLIT:g} s; nothing to vary")
    return text.replace(train_w, f"window = [0.0, {split}]").replace(lags_w, f"window = [{split}, 16.0]")


def score(model, rec, backend: str) -> dict:
    """Linearised free run of one record (from rest, or from its measured outputs): fit, coverage, sharpness."""
    measured = rec.meta.get("initial") == "measured"
    y0 = rec.y[:model.ny] if measured else None
    run = model._simulate(rec.u, 0, 0, y0, 0.99, "linear", False, False, None, 0, backend)  # eq. 8-9's band
    part = slice(model.ny if measured else 0, None)
    with np.errstate(all="ignore"):
        f = fit_percent(rec.y[part], run.mean[part])
    inside = (rec.y >= run.lower) & (rec.y <= run.upper)
    return {"fit": float(f) if np.isfinite(f) else None, "coverage": float(100.0 * np.mean(inside)),
            "half_width_over_std": float(np.mean(run.upper - run.lower) / 2.0 / max(float(np.std(rec.y)), 1e-300)),
            "seconds": float(run.seconds)}


def run_split_study(config, plan, out: Path, fit_backend: str = "jax", sim_backend: str = "jax", log=print) -> dict:
    text = Path(config).read_text()
    out.mkdir(parents=True, exist_ok=True)
    result = {"config": Path(config).name, "fit_backend": fit_backend, "sim_backend": sim_backend, "cells": []}
    for split, mode, n, m_inducing in plan:
        path = out / f"config-split-{split:g}.toml"
        path.write_text(split_config_text(text, split))
        cfg = load_config(path)
        train, lags, validate = (cfg.records_for(r) for r in ("train", "lags", "validate"))
        t0 = time.perf_counter()
        over = {"mode": mode, "max_train_points": n, "fit_backend": fit_backend}
        if mode == "sparse":
            over["inducing"] = m_inducing
        model = model_from_config(cfg, **over).fit(train, heldout=lags)
        cell = {"noise_split": split, "mode": mode, "n_train": int(model.n_train_), "inducing": m_inducing,
                "fit_seconds": time.perf_counter() - t0, "noise_var": float(model.noise_var_),
                "lags": {r.name: score(model, r, sim_backend) for r in lags},
                "validate": {r.name: score(model, r, sim_backend) for r in validate}}
        cell["worst_lags_fit"] = min((v["fit"] for v in cell["lags"].values() if v["fit"] is not None), default=None)
        result["cells"].append(cell)
        (out / "split_study.json").write_text(json.dumps(result, indent=1))
        log(f"split {split:g} s {mode} N {n} M {m_inducing}: worst lags fit {cell['worst_lags_fit']:.1f}; held out "
            + " ".join(f"{k} {v['fit']:.1f}" for k, v in cell["validate"].items()))
    return result


def markdown(result: dict, arx_fits: dict | None = None) -> str:
    """The study as a table: one row per cell, the worst 'lags' fit, then each held-out record's fit (coverage)."""
    cells = result["cells"]
    names = list(cells[0]["validate"]) if cells else []
    head = "| noise split s | posterior | worst lags fit % | " + " | ".join(names) + " |"
    lines = [head, "|" + "---|" * (3 + len(names))]
    for c in cells:
        post = f"exact, N = {c['n_train']}" if c["mode"] == "exact" else f"sparse, M = {c['inducing']}"
        vals = [f"{v['fit']:.1f} ({v['coverage']:.0f} %)" if v["fit"] is not None else "n/a"
                for v in c["validate"].values()]
        worst = "n/a" if c["worst_lags_fit"] is None else f"{c['worst_lags_fit']:.1f}"
        lines.append(f"| {c['noise_split']:g} | {post} | {worst} | " + " | ".join(vals) + " |")
    if arx_fits:
        lines.append("| | better ARX | | " + " | ".join(
            "n/a" if arx_fits.get(n) is None else f"{arx_fits[n]:.1f}" for n in names) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config")
    ap.add_argument("--out", required=True)
    ap.add_argument("--plan", default=DEFAULT_PLAN)
    ap.add_argument("--fit-backend", default="jax", choices=("numpy", "jax"))
    ap.add_argument("--sim-backend", default="jax", choices=("numpy", "jax"))
    a = ap.parse_args(argv)
    run_split_study(a.config, parse_plan(a.plan), Path(a.out), a.fit_backend, a.sim_backend)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
