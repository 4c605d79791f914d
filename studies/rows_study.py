"""Do more training rows improve the real rig's free run? Exact GP-NARX at growing N against the shipped model.

For each N in ``sizes``: the config's model in exact mode with ``max_train_points = N`` (the config's
selection of the training rows), ML-II (eq. 13) and the posterior's solves on ``fit_backend`` (on a GPU,
``jax`` makes N of 10-20 thousand a matter of seconds), the config's noise calibration on its 'lags'
records, then the linearised free run of every 'validate' record, whole and from rest, on
``sim_backend``: its fit (eq. 14, %) and the band's coverage. The config's own model (``reference``,
e.g. the shipped sparse one loaded from its bundle) is scored the same way. The free-run band here is
eq. 8-9's alone (no discrepancy term), so the coverages compare the posteriors themselves.

    python -m studies.rows_study CONFIG --sizes 1500,6000,16000 --out DIR [--reference BUNDLE]
        [--fit-backend jax] [--sim-backend jax]

Writes DIR/rows_study.json after every size (a run cut short keeps what it measured).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gpnarx.training.config import load_config
from gpnarx.training.prepare import model_from_config
from studies.split_study import score  # a record's linearised run: fit, coverage, sharpness


def run_rows_study(config, sizes, out: Path, reference=None, fit_backend: str = "jax",
                   sim_backend: str = "jax", log=print) -> dict:
    cfg = load_config(config)
    train, lags, validate = (cfg.records_for(r) for r in ("train", "lags", "validate"))
    result = {"config": cfg.name, "fit_backend": fit_backend, "sim_backend": sim_backend,
              "validate": [r.name for r in validate], "rows": []}
    out.mkdir(parents=True, exist_ok=True)

    def save():
        (out / "rows_study.json").write_text(json.dumps(result, indent=1))

    if reference is not None:
        from ..model.bundle import load_bundle

        ref = load_bundle(reference).model
        result["reference"] = {"what": f"{cfg.name} bundle ({ref.posterior_.kind}, {ref.posterior_.n_points} points, "
                                       f"ML-II on {ref.n_train_} rows)",
                               "records": {r.name: score(ref, r, sim_backend) for r in validate}}
        log(f"reference {result['reference']['what']}: "
            + " ".join(f"{k} {v['fit']:.1f}" for k, v in result["reference"]["records"].items()))
        save()
    noise_cal = cfg.model.get("noise_calibration", "none") == "lags"
    for n in sizes:
        t0 = time.perf_counter()
        m = model_from_config(cfg, mode="exact", max_train_points=int(n), fit_backend=fit_backend)
        m.fit(train, heldout=lags if noise_cal else None)
        fit_s = time.perf_counter() - t0
        row = {"n_train": int(m.n_train_), "n_rows": int(m.n_rows_), "fit_seconds": fit_s, "nlml": float(m.nlml_),
               "noise_var": float(m.noise_var_), "records": {r.name: score(m, r, sim_backend) for r in validate}}
        fits = [v["fit"] for v in row["records"].values() if v["fit"] is not None]
        row["worst_fit"] = min(fits) if fits else None
        row["mean_fit"] = float(np.mean(fits)) if fits else None
        result["rows"].append(row)
        log(f"N {m.n_train_}: fit {fit_s:.0f} s, " + " ".join(f"{k} {v['fit']:.1f}" for k, v in row["records"].items()))
        save()
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config")
    ap.add_argument("--sizes", default="1500,6000,16000")
    ap.add_argument("--out", required=True)
    ap.add_argument("--reference")
    ap.add_argument("--fit-backend", default="jax", choices=("numpy", "jax"))
    ap.add_argument("--sim-backend", default="jax", choices=("numpy", "jax"))
    a = ap.parse_args(argv)
    run_rows_study(a.config, [int(s) for s in a.sizes.split(",")], Path(a.out), a.reference, a.fit_backend,
                   a.sim_backend)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
