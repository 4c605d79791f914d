"""Simulated records from a specification: the per-system defaults of the paper's protocols and
the excitation each spec describes (shared by ``gpnarx simulate`` and dataset configs).

Units: frequencies [Hz], rates [Hz/s], durations [s], fs [Hz]; amplitudes in the system's input unit
(Bouc-Wen force [N], BERT stand-in shaker voltage [V]).
"""
from __future__ import annotations

import numpy as np

from gpnarx.training import excitations as ex

SYSTEMS = ("bouc-wen", "bert-standin")
EXCITATIONS = ("sweep", "sine", "multisine", "noise")

#: Per-system defaults (Hz, Hz/s, s, samples).
DEFAULTS = {
    "bouc-wen": {
        "fs": 750.0,
        "units": {"u": "N", "y": "m"},
        "sweep": {"f0": 5.0, "f1": 150.0, "rate": 53.0, "duration": None},  # None: the sweep's length
        "sine": {"freq": 35.59, "duration": 2.0},
        "multisine": {"f0": 5.0, "f1": 150.0, "duration": 8192 / 750.0},
        "noise": {"f0": 5.0, "f1": 150.0, "duration": 8192 / 750.0},
        "preroll": 8.0,
    },
    "bert-standin": {
        "fs": 1024.0,
        "units": {"u": "V", "y": "m/s"},
        "sweep": {"f0": 0.0, "f1": 40.0, "rate": 5.0, "duration": 16.0},
        "sine": {"freq": 18.0, "duration": 16.0},
        "multisine": {"f0": 0.0, "f1": 40.0, "duration": 16.0},
        "noise": {"f0": 0.0, "f1": 110.0, "duration": 16.0},
        "preroll": 10.0,
    },
}
SINE_TAIL = 0.25  # s simulated after a steady sine record and cut off (input interpolation end effects)

# options each excitation uses (others are rejected rather than silently ignored; --seed is always
# accepted: it seeds the multisine phases, the noise excitation, the output noise and the stand-in)
USES = {
    "sweep": {"f0", "f1", "rate", "duration"},
    "sine": {"freq", "duration"},
    "multisine": {"f0", "f1", "duration"},
    "noise": {"f0", "f1", "duration"},
}



def excitation(spec: dict, fs: float) -> tuple[np.ndarray, dict]:
    """Input samples of the returned record and a dict of the settings actually used."""
    exc, a = spec["excitation"], spec["amplitude"]
    if exc == "sweep":
        f0, f1, rate = spec["f0"], spec["f1"], spec["rate"]
        sweep = ex.swept_sine(fs, a, f0, f1, rate=rate)
        duration = spec["duration"]
        n = sweep.size if duration is None else ex.n_samples(fs, duration)
        u = np.zeros(n)
        m = min(n, sweep.size)
        u[:m] = sweep[:m]
        f_end = min(f1, f0 + rate * (m - 1) / fs)
        return u, {"f0": f0, "f1": f1, "rate": rate, "f_end": f_end}
    if exc == "sine":
        ex.sine(fs, a, spec["freq"], 1.0 / fs)  # validates freq against fs
        return ex.sine(fs, a, spec["freq"], spec["duration"]), {"freq": spec["freq"]}
    if exc == "multisine":
        n = ex.n_samples(fs, spec["duration"])
        u = ex.multisine(fs, a, spec["f0"], spec["f1"], n, seed=spec["seed"])
        lines = ex.multisine_lines(fs, spec["f0"], spec["f1"], n)
        return u, {"f0": spec["f0"], "f1": spec["f1"], "n_per_period": n, "n_lines": int(lines.size)}
    u = ex.band_limited_noise(fs, spec["duration"], spec["f0"], spec["f1"], a, seed=spec["seed"])
    return u, {"f0": spec["f0"], "f1": spec["f1"]}



def sine_padding(fs: float, preroll: float) -> tuple[int, int]:
    """Pre-roll and tail lengths [samples] of a steady sine."""
    return int(round(preroll * fs)), int(round(SINE_TAIL * fs))


def padded_sine(spec: dict, fs: float, n: int, pre: int, tail: int) -> np.ndarray:
    """The same sine from sample -pre to n + tail (sample 0 at phase 0)."""
    k = np.arange(-pre, n + tail, dtype=np.float64)
    return spec["amplitude"] * np.sin(2.0 * np.pi * spec["freq"] * k / fs)
