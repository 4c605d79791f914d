"""A first run of ``configs/bert-real-sensors.toml`` (issue 52): the shaker voltage in, the laser and the four
accelerometers out, one GP per output (``MIMOGPNARX``), scored per channel against a linear ARX per channel and
one over every channel's lags, on every record of the config.

    python studies/bert_real_sensors.py [--seconds S] [--out docs/runs/bert-real-sensors]

trains into a temporary registry (``training.pipeline.train``, which hands the config to
``training.mimo_pipeline.train_mimo``), every record whole (``--seconds S``: cut to its first S seconds, a quicker
look; 16 s took 261-396 s, whole records 575 s on the shared 2-core machine at load 7-9), and stores
``report.json`` (the
bundle's per-channel metrics), ``summary.json`` (fit and coverage per record and channel, and the ARX fits) and
the figures of one record of each validation class (``FIGURES``).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

from gpnarx.configs import shipped_config
from gpnarx.training.pipeline import train

#: the figures stored: one record of each validation class (near resonance, a sweep, broadband noise)
FIGURES = ("heldout-20Hz", "heldout-sweep-0p10V", "heldout-noise-0p10V")


def store(report: Path, out: Path) -> None:
    """The bundle's report folder into ``out``: report.json and the ``FIGURES`` (palette PNGs, a quarter the size)."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(report / "report.json", out / "report.json")
    for name in FIGURES:
        Image.open(report / f"{name}.png").convert("RGB").quantize(colors=32).save(out / f"{name}.png", optimize=True)


def run(seconds: float | None, out: Path) -> dict:
    with tempfile.TemporaryDirectory() as reg:
        res = train(shipped_config("bert-real-sensors"), reg, max_seconds=seconds, log=print)
        store(Path(res["path"]) / "report", out)
    m = res["metrics"]
    summarise(m, seconds, out)
    return m


def summarise(m: dict, seconds: float | None, out: Path) -> dict:
    """summary.json: fit and coverage per record and channel beside the two ARX fits."""
    summary = {"seconds": seconds, "fit_seconds": m["fit_seconds"], "wall_seconds": m["wall_seconds"],
               "method": m["method"], "channels": [c["name"] for c in m["channels"]["outputs"]], "records": {}}
    for name, r in m["records"].items():
        if "channels" not in r:
            continue
        own = r["baselines"].get("linear ARX per channel", {})
        summary["records"][name] = {
            "role": r["role"],
            "channels": {ch: {"fit": v["fit"], "coverage": v["coverage"],
                              "arx_fit": r["baselines"]["linear ARX"][ch]["fit"],
                              "arx_channel_fit": own.get(ch, {}).get("fit")}
                         for ch, v in r["channels"].items()}}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=0.0, help="cut every record to its first S seconds (0: whole)")
    ap.add_argument("--out", type=Path, default=Path("docs/runs/bert-real-sensors"))
    a = ap.parse_args(argv)
    m = run(a.seconds or None, a.out)
    print(f"RESULT wall_seconds={m['wall_seconds']:.0f} records={len(m['records'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
