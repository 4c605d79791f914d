"""The band's discrepancy window, centred against trailing: coverage, sharpness and streams.

The model-discrepancy term of the band (``model.discrepancy``) scales with the local RMS amplitude of the
predicted mean over a window. A centred window needs half a window of the future, so a stream's chunk
cannot compute it at its end; a trailing (causal) window can, and then a record predicted in chunks gets
the whole record's band. This study asks what the causal window costs in band quality. For each config:

1. a fitted model: trained from the shipped config with ``band_calibration = "lags"`` and
   ``band_window_kind = "trailing"`` added (a temporary copy of the config, into a temporary registry:
   the stored ``band_discrepancy`` is read back from the bundle), or a bundle already trained from it
   (``--bundle CONFIG=REGISTRY``, e.g. ``bert-real``, whose config already calibrates the band; a
   training run stored before is kept in the run file as ``training_check``);
2. the scale calibrated with each window kind on the config's ``lags`` records (the training's own
   ``calibrate_band_from_config``; the fit itself does not depend on the window);
3. every report record (roles verify and validate), predicted linearised with each calibration, with the
   report's start rule: coverage of the measured record by the band [%] and the band's mean half-width
   (sharpness, in the record's output units and relative to its RMS);
4. the scale each kind needs for every report record to reach the band's confidence (calibrated on the
   report records themselves: not a held-out claim, a comparison of the windows' shapes at equal
   coverage) and the band's half-width then;
5. one report record in 1 s chunks with the trailing kind, each chunk continuing the previous one's
   state: the largest difference of mean and band edges from the whole record's run.

Writes ``docs/runs/band-window/<config>.json`` and renders ``docs/band-window.md`` from every stored run.

    python studies/band_window_study.py [--configs bouc-wen bert-standin] [--bundle bert-real=REGISTRY]
    python studies/band_window_study.py --render-only
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gpnarx.model.discrepancy import calibrate_scale, widen_chunk

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "docs" / "runs" / "band-window"
PAGE = ROOT / "docs" / "band-window.md"
# the windows compared: name -> (kind, length as a fraction of the config's band_window)
VARIANTS = {"centred": ("centred", 1.0), "trailing": ("trailing", 1.0), "trailing_half": ("trailing", 0.5)}


def _trailing_copy(name: str, folder: Path) -> Path:
    """The shipped config ``name`` with the band calibrated on its lags records, trailing window."""
    text = (ROOT / "configs" / f"{name}.toml").read_text()
    text = re.sub(r"(?m)^band_calibration\s*=.*\n", "", text)
    text = re.sub(r"(?m)^band_window_kind\s*=.*\n", "", text)
    text = re.sub(r"(?m)^\[model\]\s*\n", '[model]\nband_calibration = "lags"\nband_window_kind = "trailing"\n',
                  text, count=1)
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def _start(model, rec):
    return rec.y[: model.ny] if rec.meta.get("initial") == "measured" and rec.y is not None else None


def _raw_runs(model, recs) -> list:
    """(name, y, linearised run without the discrepancy term, skipped start samples) of each record."""
    disc, model.band_discrepancy_ = model.band_discrepancy_, None
    try:
        out = []
        for rec in recs:
            skip = model.ny if rec.meta.get("initial") == "measured" else 0
            out.append((rec.name, np.asarray(rec.y, float),
                        model.simulate(rec.u, method="linear", y0=_start(model, rec)), skip))
        return out
    finally:
        model.band_discrepancy_ = disc


def _quality(runs, disc: dict) -> dict:
    """Coverage [%], mean half-width (output units, and over the record's RMS) and RMSE of each run with the
    discrepancy ``disc`` added as the model adds it to a whole record."""
    out = {}
    for name, y, raw, skip in runs:
        run = widen_chunk(raw, disc)[0]
        yy, lo, hi, m = y[skip:], run.lower[skip:], run.upper[skip:], run.mean[skip:]
        half = float(np.mean(hi - lo) / 2.0)
        out[name] = {"coverage": 100.0 * float(np.mean((yy >= lo) & (yy <= hi))), "half_width": half,
                     "half_width_rel_rms": half / float(np.sqrt(np.mean(yy * yy))),
                     "rmse": float(np.sqrt(np.mean((yy - m) ** 2)))}
    return out


def _stream_check(model, rec) -> dict:
    n = int(round(rec.fs))
    whole = model.simulate(rec.u, method="linear")
    parts, state = [], None
    for c in range(0, rec.u.size, n):
        r = model.simulate(rec.u[c:c + n], method="linear", state=state, open_end=c + n < rec.u.size)
        parts.append(r)
        state = r.state
    cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "lower", "upper")}
    half = np.maximum((whole.upper - whole.lower) / 2.0, 1e-300)
    band = np.maximum(np.abs(cat["lower"] - whole.lower), np.abs(cat["upper"] - whole.upper)) / half
    return {"record": rec.name, "chunk_samples": n, "chunks": len(parts),
            "max_mean_diff": float(np.max(np.abs(cat["mean"] - whole.mean))),
            "max_band_diff_rel_half_width": float(np.max(band))}


def study(name: str, bundle_registry: str | None) -> dict:
    from gpnarx.storage.registry import Registry
    from gpnarx.training.config import load_config
    from gpnarx.training.pipeline import calibrate_band_from_config, train

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        if bundle_registry:
            cfg = load_config(ROOT / "configs" / f"{name}.toml")
            reg, how = bundle_registry, f"bundle trained from configs/{name}.toml"
        else:
            cfg = load_config(_trailing_copy(name, Path(tmp)))
            reg = str(Path(tmp) / "registry")
            train(cfg, reg, report=False, report_method="linear", log=lambda msg: print("  " + msg, flush=True))
            how = f"trained from configs/{name}.toml with band_calibration = \"lags\", band_window_kind = \"trailing\""
        bundle = Registry(reg, lazy=True).scan(only=name).get(name)
        model = bundle.model
        stored = dict(model.band_discrepancy_ or {})
        held = cfg.records_for("lags")
        report = [r for role in ("verify", "validate") for r in cfg.records_for(role)]
        report = list({r.name: r for r in report}.values())
        res = {"config": name, "how": how, "fs": cfg.fs, "ny": model.ny, "nu": model.nu,
               "stored_band_discrepancy": {k: stored.get(k) for k in ("scale", "window", "window_kind")},
               "kinds": {}, "needed": {}}
        runs = _raw_runs(model, report)
        seconds = float(cfg.model.get("band_window", 0.25))
        for variant, (kind, share) in VARIANTS.items():
            cfg.model["band_window_kind"], cfg.model["band_window"] = kind, seconds * share
            d = calibrate_band_from_config(model, cfg, held)
            res["kinds"][variant] = {"kind": kind, "scale": d["scale"], "window": d["window"], "reached": d["reached"],
                                     "calibration_coverage": d["coverage_after"], "records": _quality(runs, d)}
            if variant == "trailing":
                res["stream"] = _stream_check(model, report[0])
            # the scale each window needs for every report record to reach the band's confidence, and the
            # band that gives: the windows' shapes compared at equal coverage
            need = calibrate_scale([(n_, y, r, k) for n_, y, r, k in runs], d["window"], kind=kind)
            res["needed"][variant] = {"scale": need["scale"], "reached": need["reached"],
                                      "records": _quality(runs, {**need, "window_kind": kind})}
        cfg.model["band_window"] = seconds
    res["seconds"] = time.perf_counter() - t0
    return res


def render() -> str:
    runs = [json.loads(p.read_text()) for p in sorted(RUNS.glob("*.json"))]
    lines = ["# The band's discrepancy window: centred or trailing", "",
             "Rendered by `python studies/band_window_study.py` from `docs/runs/band-window/*.json`. The band's",
             "model-discrepancy term (`model/discrepancy.py`) grows with the local RMS amplitude of the predicted",
             "mean over a window (`band_window`, 0.25 s). `band_window_kind = \"trailing\"` puts that window on the",
             "samples up to each sample, so a record sent in chunks (a stream, docs/api.md) gets the whole record's",
             "band; `\"centred\"` (the default, and every bundle calibrated before the choice) needs half a window",
             "of the record still to come. A centred window looks half a window back; a trailing window of half",
             "the length (`band_window = 0.125`) looks as far back and no further. Each window's scale is",
             "calibrated on the config's `lags` records (the worst record reaches the band's confidence); the",
             "report records (verify, validate) are then predicted linearised with each. Coverage [%] of the",
             "measured record by the 99 % band, and the band's mean half-width relative to the record's RMS",
             "(sharpness: smaller is sharper).", ""]
    names = {"centred": "centred", "trailing": "trailing", "trailing_half": "trailing, half window"}
    for r in runs:
        ks = [v for v in names if v in r["kinds"]]
        c, s = r["kinds"]["centred"], r["stream"]
        lines += [f"## {r['config']}", "", f"{r['how']}; ny={r['ny']}, nu={r['nu']}, fs {r['fs']:g} Hz.", "",
                  "Calibrated on the `lags` records (as training does): scale of the local amplitude, "
                  + ", ".join(f"{names[v]} {r['kinds'][v]['scale']:.4g} ({r['kinds'][v]['window']} samples)"
                              for v in ks) + ".", "",
                  "| record | " + " | ".join(f"coverage {names[v]}" for v in ks) + " | "
                  + " | ".join(f"half-width/RMS {names[v]}" for v in ks) + " |",
                  "|---|" + "---|" * (2 * len(ks))]
        for name in c["records"]:
            q = [r["kinds"][v]["records"][name] for v in ks]
            lines.append(f"| {name} | " + " | ".join(f"{x['coverage']:.2f}" for x in q) + " | "
                         + " | ".join(f"{x['half_width_rel_rms']:.4f}" for x in q) + " |")
        lines += [""]
        for v in ks[1:]:
            hw = [r["kinds"][v]["records"][k]["half_width"] / q["half_width"] for k, q in c["records"].items()]
            worst = min(q["coverage"] for q in r["kinds"][v]["records"].values())
            lines.append(f"- {names[v]}: worst coverage {worst:.2f} % "
                         f"(centred {min(q['coverage'] for q in c['records'].values()):.2f} %); half-width over the "
                         f"centred one's {min(hw):.3f} to {max(hw):.3f} (median {float(np.median(hw)):.3f}).")
        if all(r["kinds"][v]["scale"] == 0 for v in ks):
            lines += ["", "The `lags` records are covered without the term (scale 0 with every window): the windows "
                      "give the same band on this model as shipped."]
        if r.get("needed"):
            nc = r["needed"]["centred"]
            lines += ["", "At equal coverage: the scale each window needs for every report record to reach 99 % "
                      "(calibrated on the report records themselves: not a held-out claim, a comparison of the "
                      "windows' shapes), and the band's half-width then over the centred window's:", ""]
            for v in ks:
                n = r["needed"][v]
                ratio = [n["records"][k]["half_width"] / q["half_width"] for k, q in nc["records"].items()]
                lines.append(f"- {names[v]}: scale {n['scale']:.4g}" + ("" if n["reached"] else " (not reached)")
                             + f", worst coverage {min(q['coverage'] for q in n['records'].values()):.2f} %, "
                             f"half-width ratio {min(ratio):.3f} to {max(ratio):.3f} (median "
                             f"{float(np.median(ratio)):.3f}).")
        if r.get("training_check"):
            tc = r["training_check"]
            lines += ["", f"Training check: {tc['how']}; the bundle read back stores "
                      f"`{json.dumps(tc['stored_band_discrepancy'])}`."]
        lines += ["", f"Stream, trailing window: `{s['record']}` in {s['chunks']} chunks of {s['chunk_samples']} "
                  f"samples (1 s) against the record whole: largest mean difference {s['max_mean_diff']:.3g}, largest "
                  f"band-edge difference {s['max_band_diff_rel_half_width']:.3g} of the half-width.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", nargs="*", default=["bouc-wen", "bert-standin"])
    p.add_argument("--bundle", action="append", default=[], help="CONFIG=REGISTRY: use a bundle trained already")
    p.add_argument("--render-only", action="store_true")
    args = p.parse_args(argv)
    if not args.render_only:
        bundles = dict(b.split("=", 1) for b in args.bundle)
        RUNS.mkdir(parents=True, exist_ok=True)
        for name in list(args.configs) + [b for b in bundles if b not in args.configs]:
            print(f"{name} ...", flush=True)
            res = study(name, bundles.get(name))
            stored = RUNS / f"{name}.json"
            if stored.exists():  # keep the record of the training run that wrote the trailing kind
                old = json.loads(stored.read_text())
                check = old.get("training_check") or (
                    {k: old[k] for k in ("how", "stored_band_discrepancy", "seconds")}
                    if old.get("how", "").startswith("trained") else None)
                if check and not res["how"].startswith("trained"):
                    res["training_check"] = check
            stored.write_text(json.dumps(res, indent=1) + "\n")
            print(json.dumps({k: res[k] for k in ("config", "stored_band_discrepancy", "stream", "seconds")}),
                  flush=True)
    PAGE.write_text(render())
    print(f"wrote {PAGE}", file=sys.stderr)


if __name__ == "__main__":
    main()
