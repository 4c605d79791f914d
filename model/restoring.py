"""Restoring force and hysteresis loops.

For a single-degree-of-freedom (or single-mode) model m x'' + R(x, x') = g u, the restoring force
is R = g u - m x'' [N]: everything the structure opposes to the applied force (linear stiffness
and damping plus the hysteretic force). For the Bouc-Wen benchmark, m = 2 kg, g = 1 N/N, x is the
displacement output. Velocity outputs are integrated / differentiated in the frequency domain
(drift-free: components below ``f_highpass`` are removed).
"""
from __future__ import annotations

import numpy as np


def _fft_derivative(x: np.ndarray, fs: float, order: int, f_highpass: float = 0.0) -> np.ndarray:
    """Frequency-domain derivative (order > 0) or integral (order < 0) of x sampled at fs [Hz]."""
    n = x.size
    X = np.fft.rfft(x - np.mean(x))
    f = np.fft.rfftfreq(n, 1.0 / fs)
    jw = 2j * np.pi * f
    with np.errstate(divide="ignore", invalid="ignore"):
        H = jw ** order
    H[0] = 0.0
    if f_highpass > 0:
        H[f < f_highpass] = 0.0
    return np.fft.irfft(X * H, n)


def kinematics(y: np.ndarray, fs: float, output: str = "displacement", f_highpass: float = 1.0):
    """(displacement [m], acceleration [m/s^2]) from an output that is displacement or velocity."""
    y = np.asarray(y, float)
    if output == "displacement":
        return y, _fft_derivative(y, fs, 2)
    if output == "velocity":
        return _fft_derivative(y, fs, -1, f_highpass), _fft_derivative(y, fs, 1)
    raise ValueError(f"output must be 'displacement' or 'velocity', got {output!r}")


def restoring_force(u, y, fs: float, mass: float, input_gain: float = 1.0, output: str = "displacement",
                    f_highpass: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(displacement [m], restoring force R = g u - m x'' [N])."""
    if mass <= 0:
        raise ValueError(f"mass must be positive (kg), got {mass}")
    x, acc = kinematics(y, fs, output, f_highpass)
    return x, input_gain * np.asarray(u, float) - mass * acc


def loop_units(units: dict | None, physics: dict | None) -> dict:
    """Units of a loop from a bundle's ``units`` and ``physics``: ``{"x", "force", "energy",
    "stiffness"}``. x is the output's unit (displacement output) or the output's unit without "/s"
    (velocity output, integrated); the force R = g u - m x'' is in N whatever the input's unit
    (g converts it: N/N or N/V), energy in N x the x unit (J for m), stiffness in N per x unit."""
    yu = str((units or {}).get("y") or "m")
    output = (physics or {}).get("output", "displacement")
    x = yu if output == "displacement" else (yu[:-2] if yu.endswith("/s") else "m")
    x = x or "m"
    return {"x": x, "force": "N", "energy": "J" if x == "m" else f"N {x}", "stiffness": f"N/{x}"}


def loop_area(x, r) -> float:
    """Area enclosed by the (x, R) trajectory (energy dissipated, J), by the shoelace formula."""
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    return float(0.5 * abs(np.sum(x * np.roll(r, -1) - np.roll(x, -1) * r)))
