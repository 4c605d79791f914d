"""How far the linearised band moves when eq. 9's latent variance is evaluated at every s-th step only and
linearly interpolated between (``RunSpec.variance_stride``), on every real record of the lab data.

For each record (every LMS folder under the data directory, ``real_table.find_records``): the linearised free run
of the whole record from rest with the bundle's model, at stride 1 (exact: eq. 9 at every step) and at each
stride asked; the band's largest difference from the exact one, relative to the exact band's half-width at the
same sample: max_i max(|lower_s - lower_1|, |upper_s - upper_1|) / ((upper_1 - lower_1) / 2), for the GP's own
band (``gp``) and for the band the product answers with (``product``: widened by the bundle's model-discrepancy
term, ``model.discrepancy``, where it has one). Also the free run's seconds at each stride, on this machine.

    python studies/variance_stride_study.py --registry R [--model bert-real] [--data DIR] [--strides 2,4,8]
        [--out docs/runs/variance-stride/table.json] [--render docs/numerics.md]
    python studies/variance_stride_study.py --render docs/numerics.md --from-run docs/runs/variance-stride/table.json

``--render PAGE`` splices the table into PAGE's block (``gpnarx.training.pages.variance_stride``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def band_difference(exact, strided) -> float:
    """The largest |edge difference| of ``strided``'s band from ``exact``'s, relative to exact's half-width."""
    half = 0.5 * (exact.upper - exact.lower)
    diff = np.maximum(np.abs(strided.lower - exact.lower), np.abs(strided.upper - exact.upper))
    ok = half > 0
    return float(np.max(diff[ok] / half[ok])) if np.any(ok) else 0.0


def study(registry: str, name: str, data_dir, strides: list[int], log=print) -> dict:
    from dataclasses import replace

    from gpnarx.model.discrepancy import widen_chunk
    from gpnarx.model.freerun import RunSpec, run
    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.record_files import read_record
    from gpnarx.storage.registry import Registry
    from studies.real_table import find_records

    tune_for_free_run(None)
    bundle = Registry(registry).scan().get(name)
    model = bundle.model
    predictor = model.predictor()
    disc = getattr(model, "band_discrepancy_", None)
    base = RunSpec(method="linear", include_noise=model.include_noise)
    rows = []
    for folder in find_records(data_dir):
        rec = read_record(str(folder), fs_default=bundle.fs)
        runs, secs = {}, {}
        for s in [1] + strides:
            t0 = time.perf_counter()
            runs[s] = run(predictor, rec.u, replace(base, variance_stride=s))
            secs[s] = time.perf_counter() - t0
        product = {s: widen_chunk(r, disc)[0] for s, r in runs.items()} if disc else runs
        row = {"record": str(Path(folder).relative_to(data_dir)), "n": int(rec.u.size), "fs": float(rec.fs),
               "seconds": {str(s): secs[s] for s in runs},
               "gp": {str(s): band_difference(runs[1], runs[s]) for s in strides},
               "product": {str(s): band_difference(product[1], product[s]) for s in strides}}
        rows.append(row)
        log(f"{row['record']}: " + ", ".join(f"s={s}: gp {100 * row['gp'][str(s)]:.3f} %, product "
                                             f"{100 * row['product'][str(s)]:.3f} %" for s in strides))
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    return {"model": f"{name}:{bundle.version}", "posterior": model.posterior_.kind,
            "n_points": int(model.posterior_.n_points), "ny": int(model.ny), "nu": int(model.nu),
            "discrepancy": bool(disc), "strides": strides, "records": rows, "code": commit,
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "load": os.getloadavg()[0],
            "bound": 0.01}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--registry", help="registry holding the model")
    ap.add_argument("--model", default="bert-real")
    ap.add_argument("--data", default=None, help="lab data folder (default: the package's lookup)")
    ap.add_argument("--strides", default="2,4,8")
    ap.add_argument("--out", default=str(ROOT / "docs" / "runs" / "variance-stride" / "table.json"))
    ap.add_argument("--from-run", default=None, help="render a stored run instead of computing one")
    ap.add_argument("--render", default=None, help="page whose block to re-render (docs/numerics.md)")
    args = ap.parse_args(argv)
    if args.from_run:
        table = json.loads(Path(args.from_run).read_text())
    else:
        if not args.registry:
            ap.error("--registry is required unless --from-run")
        from gpnarx.training.datapaths import bert_data_dir

        data = Path(args.data) if args.data else bert_data_dir()
        table = study(args.registry, args.model, data, [int(s) for s in args.strides.split(",")])
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(table, indent=1) + "\n")
        print(f"wrote {out}")
    if args.render:
        from gpnarx.training.pages.markdown import replace_block
        from gpnarx.training.pages.variance_stride import BEGIN, END, render

        page = Path(args.render)
        page.write_text(replace_block(page.read_text(), BEGIN, END, render(table)))
        print(f"rendered {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
