"""An update from a new healthy recording on the real rig: before and after, scored on the held-out records.

The shipped ``configs/bert-real.toml`` without one training sine (``--hold``, default the 19 Hz sine: its start-up,
steady and decay windows) is trained (``training.pipeline.train``, no report); that version is then updated with
the held-back sine's three windows, as new records (``training.update.update``, the code of ``gpnarx update``, with
the variant config for the recalibrations). Both versions, and optionally a reference bundle trained with the sine
(``--reference``, e.g. the shipped bert-real), are scored on every ``validate`` record of the config, which no choice
saw: the linearised free run of the config's ``[predict]`` settings from each record's start rule, fit % (eq. 14)
and 99 % coverage (``pipeline.evaluate_record``, ``basic_metrics``: what the training report scores).

Writes ``docs/runs/update/bert-real-hold-19Hz.json``; ``training/pages/update.py`` renders it into docs/updates.md:

    GPNARX_BERT_DATA=... python studies/update_study.py [--hold 19Hz] [--reference REGISTRY/bert-real/1]
    python -m gpnarx.training.pages.update docs/runs/update/bert-real-hold-19Hz.json docs/updates.md
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def variant_config(text: str, hold: str) -> tuple[str, list[str]]:
    """The config text without the ``train-{hold}-*`` records, named ``bert-real-no-{hold}``; and the names held."""
    blocks = re.split(r"(?m)^(?=\[\[records\]\])", text)
    kept, held = [blocks[0]], []
    for b in blocks[1:]:
        m = re.search(r'(?m)^name = "([^"]+)"', b)
        if m and m.group(1).startswith(f"train-{hold}-"):
            held.append(m.group(1))
        else:
            kept.append(b)
    if not held:
        raise SystemExit(f"--hold {hold}: no train-{hold}-* records in the config")
    out = "".join(kept).replace('name = "bert-real"', f'name = "bert-real-no-{hold}"', 1)
    return out, held


def score(model, cfg, plan) -> dict:
    from gpnarx.training.pipeline import basic_metrics, evaluate_record

    out = {}
    for k, rec in enumerate(cfg.records_for("validate")):
        ev = evaluate_record(model, rec, "validate", plan["mc_paths"], seed=k, confidence=plan["confidence"],
                             method=plan["method"])
        met = basic_metrics(ev)
        out[rec.name] = {"fit": met["fit"], "coverage": met["coverage"], "n": int(rec.n)}
        print(f"    {rec.name}: fit {met['fit']:.2f} %, coverage {met['coverage']:.2f} %", file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hold", default="19Hz", help="the training sine held back (train-HOLD-* records; default 19Hz)")
    ap.add_argument("--reference", default=None, help="a bundle trained with every record, scored beside")
    ap.add_argument("--out", default=str(ROOT / "docs" / "runs" / "update"), help="folder of the stored run")
    args = ap.parse_args(argv)
    os.environ.setdefault("GPNARX_BERT_DATA", str(ROOT.parent / "shared" / "data" / "bert-t5nm"))

    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.bundle import load_bundle
    from gpnarx.training.config import load_config
    from gpnarx.training.pipeline import train
    from gpnarx.training.update import update

    tune_for_free_run(None)
    full_path = ROOT / "configs" / "bert-real.toml"
    full = load_config(full_path)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        text, held = variant_config(full_path.read_text(), args.hold)
        vpath = tmp / f"bert-real-no-{args.hold}.toml"
        vpath.write_text(text)
        cfg = load_config(vpath)
        plan = {"method": cfg.predict.get("method", "mc"), "mc_paths": int(cfg.predict.get("mc_paths", 1024)),
                "confidence": float(cfg.predict.get("confidence", 0.99))}
        reg = tmp / "registry"
        t = time.perf_counter()
        trained = train(cfg, reg, report=False, log=lambda m: print(m, file=sys.stderr))
        train_s = time.perf_counter() - t
        parent = load_bundle(trained["path"])
        new = [full.record(n) for n in held]
        t = time.perf_counter()
        res = update(parent, new, reg, config=cfg, log=lambda m: print(m, file=sys.stderr))
        update_s = time.perf_counter() - t
        child = load_bundle(res["path"])
        print("scoring before", file=sys.stderr)
        before = score(parent.model, cfg, plan)
        print("scoring after", file=sys.stderr)
        after = score(child.model, cfg, plan)
        reference = None
        if args.reference:
            ref = load_bundle(args.reference)
            print(f"scoring reference {ref.name}:{ref.version}", file=sys.stderr)
            reference = {"bundle": f"{ref.name}:{ref.version}", "n_train": ref.model.n_train_,
                         "scores": score(ref.model, cfg, plan)}
    run = {
        "study": "update", "config": "configs/bert-real.toml", "held_back": held,
        "variant": f"bert-real-no-{args.hold}",
        "propagation": plan, "train_seconds": train_s, "update_seconds": update_s,
        "parent": {"version": trained["version"], "n_train": parent.model.n_train_,
                   "noise_var": parent.model.noise_var_,
                   "band_scale": (parent.manifest.get("band_discrepancy") or {}).get("scale")},
        "updated": {"version": res["version"], "n_train": child.model.n_train_, "noise_var": child.model.noise_var_,
                    "band_scale": (child.manifest.get("band_discrepancy") or {}).get("scale")},
        "lineage": res["lineage"], "steps": res["seconds"],
        "before": before, "after": after, "reference": reference,
        "data": os.environ["GPNARX_BERT_DATA"].replace(str(ROOT.parent), ".."),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"bert-real-hold-{args.hold}.json"
    path.write_text(json.dumps(run, indent=1, default=float) + "\n")
    print(f"written {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
