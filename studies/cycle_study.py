"""Per-cycle energy on an independent Bouc-Wen sine, next to the simulator's own (a study script).

    python -m studies.cycle_study --registry R [--model bouc-wen] [--amplitude 50]
        [--freq 35.59] [--mc 1024] [--start measured|rest] [--method mc|linear] [--out FILE.json]

1. writes the record with the product's command, ``gpnarx simulate bouc-wen --excitation sine
   --amplitude A [--freq F]`` (a steady sine: 8 s of the same sine are simulated before it);
2. integrates the same input again with ``training.simulators.boucwen`` to get the true velocity
   v and hysteretic force z (the recorded y must be the same to 1e-12 m, checked);
3. asks the product for the loops, ``gpnarx loops --registry R --model M RECORD --json``
   (per-cycle energy with its 99 % interval across the Monte Carlo paths, measured energy);
4. computes, over each of the answer's cycles, the simulator's own dissipated energy: the loop area
   of its true restoring force, integral of (c v + k y + z) v dt, and the drive's work, integral of
   u v dt (equal over a steady cycle), by the same trapezoid rule (``model.cycles.energy_weights``),
   and the secant stiffness of the true loop (``model.cycles.secant_stiffness``);
5. prints one JSON object: per-cycle rows and the share of cycles whose interval covers the
   measured energy and the simulator's own.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from gpnarx.model.cycles import energy_weights, secant_stiffness
from gpnarx.training.simulation_specs import DEFAULTS, padded_sine, sine_padding
from gpnarx.training.simulators.boucwen import BoucWen
from studies.cli_runner import emit, run_cli


def _cli(argv: list[str]) -> dict:
    return run_cli(argv)


def truth(amplitude: float, freq: float, n: int, fs: float = 750.0) -> dict:
    """The true states of the Bouc-Wen sine record ``gpnarx simulate`` writes (same padding, same input)."""
    pre, tail = sine_padding(fs, DEFAULTS["bouc-wen"]["preroll"])
    bw = BoucWen(fs=fs)
    full = padded_sine({"amplitude": amplitude, "freq": freq}, fs, n, pre, tail)
    res = bw.simulate(full)
    sl = slice(pre, pre + n)
    return {"u": full[sl], "y": res["y"][sl], "v": res["v"][sl], "z": res["z"][sl], "model": bw}


def study(registry, model: str = "bouc-wen", amplitude: float = 50.0, freq: float = 35.59, mc: int = 1024,
          seed: int = 0, start: str = "measured", method: str = "mc", workdir=None) -> dict:
    workdir = Path(workdir or tempfile.mkdtemp(prefix="gpnarx-cycles-"))
    rec = workdir / f"boucwen-sine-{amplitude:g}N-{freq:g}Hz.npz"
    sim = _cli(["simulate", "bouc-wen", "--excitation", "sine", "--amplitude", f"{amplitude:g}", "--freq",
                f"{freq:g}", "--out", str(rec)])
    d = np.load(rec)
    u, y, fs = d["u"], d["y"], float(d["fs"])
    tr = truth(amplitude, freq, u.size, fs)
    mismatch = float(np.max(np.abs(tr["y"] - y)))
    if mismatch > 1e-12 or float(np.max(np.abs(tr["u"] - u))) > 1e-12 * amplitude:
        raise RuntimeError(f"the re-integrated record differs from gpnarx simulate's by {mismatch:g} m")
    ans = _cli(["loops", "--registry", str(registry), "--model", model, str(rec), "--mc", str(mc), "--seed", str(seed),
                "--start", start, "--method", method])
    bw = tr["model"]
    r_true = bw.c * tr["v"] + bw.k * tr["y"] + tr["z"]  # restoring force R = c v + k y + z [N]
    rows = []
    for c in ans["cycles"]:
        ts, te = c["start"] * fs, c["end"] * fs
        j0, w_r = energy_weights(r_true, fs, ts, te, 1.0, "velocity")
        _, w_u = energy_weights(u, fs, ts, te, 1.0, "velocity")
        sl = slice(j0, j0 + w_r.size)
        rows.append({**{k: c.get(k) for k in ("start", "end", "energy", "energy_lower", "energy_upper",
                                               "measured_energy", "stiffness", "stiffness_lower", "stiffness_upper",
                                               "measured_stiffness")},
                     "simulator_energy": float(w_r @ tr["v"][sl]), "drive_work": float(w_u @ tr["v"][sl]),
                     "simulator_stiffness": secant_stiffness(tr["y"], r_true, ts, te)})

    def share(key, lo="energy_lower", hi="energy_upper"):
        ok = [r[lo] <= r[key] <= r[hi] for r in rows if r[lo] is not None]
        return 100.0 * sum(ok) / len(ok) if ok else None

    e = np.array([r["energy"] for r in rows])
    es = np.array([r["simulator_energy"] for r in rows])
    em = np.array([r["measured_energy"] for r in rows])
    return {"record": str(rec), "simulate": {k: sim.get(k) for k in ("amplitude", "freq", "fs", "n", "noise_fraction")},
            "model": f"{ans['model']}:{ans['version']}", "start": start, "method": ans["method"],
            "mc_paths": ans["mc_paths"], "confidence": ans["confidence"], "units": ans["units"],
            "cycle_basis": ans["cycle_basis"], "diverged_paths": ans["diverged_paths"],
            "out_of_range": ans["out_of_range"], "n_cycles": len(rows),
            "coverage_measured": share("measured_energy"), "coverage_simulator": share("simulator_energy"),
            "stiffness_coverage_simulator": share("simulator_stiffness", "stiffness_lower", "stiffness_upper"),
            "stiffness_mean": float(np.mean([r["stiffness"] for r in rows])) if rows else None,
            "simulator_stiffness_mean": float(np.mean([r["simulator_stiffness"] for r in rows])) if rows else None,
            "energy_mean": float(e.mean()) if e.size else None,
            "simulator_energy_mean": float(es.mean()) if es.size else None,
            "measured_energy_mean": float(em.mean()) if em.size else None,
            "interval_halfwidth_rel_median": float(np.median([(r["energy_upper"] - r["energy_lower"]) / 2 / r["energy"]
                                                             for r in rows])) if rows else None,
            "max_rel_measured_vs_simulator": float(np.max(np.abs(em / es - 1))) if es.size else None,
            "cycles": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.cycle_study", description=__doc__.splitlines()[0])
    p.add_argument("--registry", required=True)
    p.add_argument("--model", default="bouc-wen")
    p.add_argument("--amplitude", type=float, default=50.0)
    p.add_argument("--freq", type=float, default=35.59)
    p.add_argument("--mc", type=int, default=1024)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start", choices=("rest", "measured"), default="measured")
    p.add_argument("--method", choices=("mc", "linear"), default="mc")
    p.add_argument("--out", default=None, help="also write the JSON here")
    a = p.parse_args(argv)
    res = study(a.registry, a.model, a.amplitude, a.freq, a.mc, a.seed, a.start, a.method)
    return emit(res, a.out)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
