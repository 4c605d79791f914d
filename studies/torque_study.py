"""Energy per cycle against the residual score as bolt-loosening indicators on the BERT stand-in
(a study script; stand-in numbers, never the rig's).

    python -m studies.torque_study --registry R [--model bert-standin-monitor]
        [--torques 4,5,7,9] [--records 20] [--mc 256] [--out FILE.json]

For each torque T [N m] and each of ``--records`` stand-in realizations (``gpnarx simulate
bert-standin --excitation sine --amplitude 0.15 --freq 9 --duration 4 --torque T --seed S
--noise-fraction 0.0004``: the monitor's probe; seeds 300 + 20 i + k, none of the monitor's own),
one Monte Carlo free run of the monitor from the record's measured outputs gives
(``model.novelty``, ``model.cycles``, as the service computes them):

* ``score``: the novelty score (the bundle's method), the residual indicator;
* ``energy``: the median over the steady cycles of the measured loop's dissipated energy [J]
  (the physical indicator; it needs the model only to cut cycles and not at all to compute);
* ``energy_ratio``: the median over the cycles of measured / predicted energy: the measured
  energy against what the healthy model expects for this very drive, and ``|log energy_ratio|``
  as a two-sided indicator (a torque change may raise or lower the dissipation).

Detection at 1 % false alarms: each indicator's threshold is fitted (log-normal, 1 % tail, never
below the largest value seen: ``model.novelty.calibrate_threshold``) on the first half of the
5 N m records; the false-alarm rate is counted on the other half, and the detection rate on all the
records of each other torque. The energy indicators are two-sided: a record is flagged when its
value leaves [1st, 99th] of the fitted healthy distribution (each tail at 0.5 %).
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from gpnarx.model.cycles import cycles
from gpnarx.model.novelty import calibrate_threshold, method_of, novelty_score, novelty_start
from gpnarx.storage.registry import Registry
from studies.cli_runner import emit, run_cli


def _simulate(torque: float, seed: int, out: Path) -> Path:
    p = out / f"standin-{torque:g}Nm-s{seed}.npz"
    run_cli(["simulate", "bert-standin", "--excitation", "sine", "--amplitude", "0.15", "--freq", "9",
             "--duration", "4", "--torque", f"{torque:g}", "--seed", str(seed), "--noise-fraction", "0.0004",
             "--out", str(p)])
    return p


def indicators(bundle, path: Path, mc: int, seed: int = 0) -> dict:
    d = np.load(path)
    u, y, fs = d["u"], d["y"], float(d["fs"])
    model = bundle.model
    run = model.simulate(u, n_paths=mc, seed=seed, y0=novelty_start(y, model.ny), keep_paths=True)
    s = novelty_score(y, run.mean, run.std, method_of(bundle.manifest.get("novelty")))
    phys = bundle.manifest["physics"]
    phys = {"mass": float(phys["mass"]), "input_gain": float(phys.get("input_gain", 1.0)),
            "output": phys.get("output", "displacement")}
    cyc = cycles(u, fs, phys, run.mean, paths=run.paths, y=y)["cycles"]
    em = np.array([c["measured_energy"] for c in cyc])
    ep = np.array([c["energy"] for c in cyc])
    inside = np.mean([c["energy_lower"] <= c["measured_energy"] <= c["energy_upper"] for c in cyc]) if cyc else None
    return {"score": s["score"], "energy": float(np.median(em)), "energy_predicted": float(np.median(ep)),
            "energy_ratio": float(np.median(em / ep)), "n_cycles": len(cyc),
            "energy_coverage": None if inside is None else 100.0 * float(inside)}


def _two_sided(values, far: float) -> tuple[float, float]:
    """[lo, hi] holding 1 - far of a log-normal fit to positive ``values`` (each tail far / 2), never
    inside the extreme values seen."""
    lv = np.log(np.asarray(values, float))
    from scipy.special import ndtri

    z = float(ndtri(1 - far / 2))
    mu, sd = float(np.mean(lv)), float(np.std(lv, ddof=1))
    return min(math.exp(mu - z * sd), float(np.exp(lv.min()))), max(math.exp(mu + z * sd), float(np.exp(lv.max())))


def study(registry, model: str = "bert-standin-monitor", torques=(4.0, 5.0, 7.0, 9.0), n_records: int = 20,
          mc: int = 256, far: float = 0.01, healthy_torque: float = 5.0, workdir=None, log=None) -> dict:
    reg = Registry(Path(registry)).scan()
    name, _, version = model.partition(":")
    bundle = reg.get(name, version or None)
    work = Path(workdir or tempfile.mkdtemp(prefix="gpnarx-torque-"))
    rows = []
    for i, t in enumerate(torques):
        for k in range(n_records):
            seed = 300 + 20 * i + k
            ind = indicators(bundle, _simulate(t, seed, work), mc, seed=k)
            rows.append({"torque": t, "seed": seed, **ind})
            if log:
                log(f"T={t:g} seed={seed}: score={ind['score']:.3g} energy={ind['energy']:.4g} "
                    f"ratio={ind['energy_ratio']:.4g}")
    healthy = [r for r in rows if r["torque"] == healthy_torque]
    half = len(healthy) // 2
    cal, held = healthy[:half], healthy[half:]
    thr = calibrate_threshold([r["score"] for r in cal], far)["threshold"]
    e_lo, e_hi = _two_sided([r["energy"] for r in cal], far)
    r_lo, r_hi = _two_sided([r["energy_ratio"] for r in cal], far)
    flags = {"score": lambda r: r["score"] > thr,
             "energy": lambda r: not e_lo <= r["energy"] <= e_hi,
             "energy_ratio": lambda r: not r_lo <= r["energy_ratio"] <= r_hi}
    per_torque = {}
    for t in torques:
        rs = held if t == healthy_torque else [r for r in rows if r["torque"] == t]
        allt = [r for r in rows if r["torque"] == t]
        per_torque[f"{t:g}"] = {
            "n": len(rs), **{f"flagged_{k}": 100.0 * sum(f(r) for r in rs) / len(rs) for k, f in flags.items()},
            "score_median": float(np.median([r["score"] for r in allt])),
            "energy_mean": float(np.mean([r["energy"] for r in allt])),
            "energy_sd": float(np.std([r["energy"] for r in allt], ddof=1)),
            "energy_ratio_median": float(np.median([r["energy_ratio"] for r in allt])),
            "energy_coverage_median": float(np.median([r["energy_coverage"] for r in allt])),
        }
    return {"model": f"{bundle.name}:{bundle.version}", "mc_paths": mc, "n_records": n_records,
            "false_alarm_rate_target": far, "healthy_torque": healthy_torque,
            "thresholds": {"score": thr, "energy": [e_lo, e_hi], "energy_ratio": [r_lo, r_hi],
                           "calibrated_on_seeds": [r["seed"] for r in cal],
                           "false_alarms_on_seeds": [r["seed"] for r in held]},
            "per_torque": per_torque, "records": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.torque_study", description=__doc__.splitlines()[0])
    p.add_argument("--registry", required=True)
    p.add_argument("--model", default="bert-standin-monitor")
    p.add_argument("--torques", default="4,5,7,9")
    p.add_argument("--records", type=int, default=20)
    p.add_argument("--mc", type=int, default=256)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    torques = tuple(float(t) for t in a.torques.split(","))
    res = study(a.registry, a.model, torques, a.records, a.mc, log=lambda m: print(m, file=sys.stderr, flush=True))
    return emit(res, a.out, shown={k: v for k, v in res.items() if k != "records"})


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
