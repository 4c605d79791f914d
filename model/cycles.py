"""Per-cycle hysteresis indicators: dissipated energy and secant stiffness of each steady cycle.

A whole-record loop area mixes start-up and steady cycles and says nothing about uncertainty. This
module cuts the steady part of a record into cycles and gives, for each, the energy dissipated over
the cycle with an interval, and the secant stiffness, for the predicted response (and the measured
one when y is known). Units follow ``model.restoring``: x in m, force in N (mass in kg, input_gain
in N per input unit), energy in J, stiffness in N/m.

Cycles (``cycle_bounds``)
-------------------------
* Sine drive (``model.probe.drive_of``: at least 80 % of the input's power at its dominant
  frequency): cycles of the drive. A sine ``A sin(2 pi f t + phase) + c`` is fitted to u at the
  dominant frequency f, and cycle k runs from one upward zero crossing of that fitted sine to the
  next, (k - phase / 2 pi) / f to (k + 1 - phase / 2 pi) / f (fractional samples). Steady part:
  the peak-to-peak displacement of the predicted mean is computed per cycle, and the steady cycles
  are the longest run at the end of the record whose peak-to-peak lies within ``STEADY_TOL`` (10 %)
  of the median over the last half of the cycles and, among those, whose mean-loop energy lies
  within ``STEADY_TOL_ENERGY`` (15 %) of its own such median (``cycles``); start-up cycles of a
  free run from rest drop out (on the Bouc-Wen 50 N sine from rest, the first two, whose drive work
  still includes the kinetic energy being built up: 44 % and 21 % above the steady cycles').
* Broadband drive (noise, multisine, sweep): there is no drive period, so the cycles are those of
  the response: from one upward zero crossing of the predicted mean displacement (mean removed) to
  the next, a crossing counting only after the displacement went below -``HYSTERESIS`` (5 %) of
  its standard deviation (noise cannot split a cycle). Every such cycle of at least
  ``MIN_CYCLE_SAMPLES`` samples is returned (a broadband response has no steady state to wait for).
The same bounds apply to the predicted mean, every Monte Carlo path and the measured record, so
their energies are comparable. Cycles keep ``STENCIL_HALF`` samples off the record's ends.

Energy of a cycle (``energy_weights``)
--------------------------------------
The dissipated energy is the loop area, the work of the restoring force over the cycle,
E = integral of R dx with R = g u - m x''. The inertial part, -m integral x'' dx = -m/2 [x'^2],
vanishes over a closed (steady) cycle, so E is computed as the work of the drive,
E = integral of g u x' dt (trapezoid rule in time, linear interpolation at the fractional cycle
ends). For a velocity output x' = y. For a displacement output it is integrated by parts,
E = [g u x] from start to end - integral of g u' x dt, with u' the 8th-order central difference
of the input. The output is never differentiated: a Monte Carlo path (and a measured record)
carries noise at every sample, which a derivative amplifies (twice differentiated, through R, it
would swamp the loop). E is then a linear function of
the output samples, E = w . y, with weights ``w`` computed once per cycle and applied to the mean,
each path and the measured record alike. For a cycle that does not close (start-up), E differs
from the loop area by the change of kinetic energy over the cycle. On a sampled sine of 21 samples
per cycle the rule is exact to about 1e-4 (tests/test_cycles.py).

Interval of the energy
----------------------
* Monte Carlo (``paths``): each path's energy w . y_path; the interval is the (1 - c)/2 and
  1 - (1 - c)/2 quantiles across the paths (c = confidence, 99 % by default). ``energy`` itself is
  the energy of the predicted mean loop.
* Linearised (``cov_band``): the linearised free run is Gaussian, and E is linear in the output,
  so E ~ N(w . mean, w' C w) with C the covariance of the cycle's output samples. Samples of one
  cycle are strongly correlated (each is fed back as a regressor), so C is not diagonal: the
  linearised free run is run with ``cov_window`` lags of covariance (at least one cycle plus the
  stencil; ``cov_window_for``, at most ``COV_WINDOW_MAX`` = 256 lags, covariance beyond taken as
  zero; ``model.freerun.simulate_linear``), and the interval is w . mean -/+ z sqrt(w' C w), z
  the two-sided normal quantile. On a small Bouc-Wen model the linearised intervals agree with the
  Monte Carlo ones to about 10 % (tests/test_cycles.py). Using the band edges' loops or
  independent samples instead would be wrong (the edges are not a path; independent samples average the noise away).

Secant stiffness (``secant_stiffness``)
---------------------------------------
(R(x_max) - R(x_min)) / (x_max - x_min) over the cycle, with x and R from
``model.restoring.restoring_force`` (frequency-domain derivatives over the whole record) and the
extremes located to a fraction of a sample by a parabola through the three samples around each.
For the Monte Carlo paths the same is computed on each path (``stiffness_lower`` and
``stiffness_upper``, quantiles across paths); R of a path holds the second derivative of its noise,
so this interval is wide when the model's noise variance is large. The linearised method gives no
stiffness interval (null).
"""
from __future__ import annotations

import math

import numpy as np

from .normal import band_z
from .probe import drive_of, sine_fit
from .restoring import restoring_force

STENCIL = np.array([4.0 / 5.0, -1.0 / 5.0, 4.0 / 105.0, -1.0 / 280.0])  # 8th-order central first derivative
STENCIL_HALF = STENCIL.size
STEADY_TOL = 0.10
STEADY_TOL_ENERGY = 0.15  # the mean loop's energy per cycle
HYSTERESIS = 0.05
MIN_CYCLE_SAMPLES = 8
COV_WINDOW_MAX = 256  # lags of output covariance the linearised method keeps for cycle energies


def cov_window_for(u, fs: float, ny: int) -> int:
    """Lags of output covariance a linearised free run needs for the cycles of record u: one drive
    period (or 1.5 periods of the dominant frequency for a broadband drive) plus the stencil,
    between ny and ``COV_WINDOW_MAX``."""
    d = drive_of(u, fs)
    f = d["frequency"]
    if not f:
        return int(ny)
    period = fs / f * (1.0 if d["kind"] == "sine" else 1.5)
    return int(min(COV_WINDOW_MAX, max(ny, math.ceil(period) + 2 * STENCIL_HALF + 3)))


def _trapezoid(ts: float, te: float) -> tuple[int, np.ndarray]:
    """(first sample, weights b) with integral_{ts}^{te} q dt = sum b_i q_{first + i} / fs for the
    piecewise-linear q through samples (ts, te in fractional samples)."""
    ia, ib = int(math.floor(ts)), int(math.floor(te))
    b = np.zeros(ib - ia + 2)
    for j in range(ia, ib + 1):
        lo, hi = max(ts, j) - j, min(te, j + 1) - j
        if hi <= lo:
            continue
        s2 = (hi * hi - lo * lo) / 2.0
        b[j - ia] += (hi - lo) - s2
        b[j + 1 - ia] += s2
    return ia, b


def energy_weights(u, fs: float, ts: float, te: float, input_gain: float = 1.0,
                   output: str = "displacement") -> tuple[int, np.ndarray]:
    """(first sample j0, weights w): the energy of the cycle [ts, te] (fractional samples) of an
    output record y is ``w @ y[j0 : j0 + w.size]`` [J] (see the module docstring)."""
    u = np.asarray(u, float)
    g = float(input_gain)
    ia, b = _trapezoid(ts, te)
    if output == "velocity":  # E = integral of g u y dt
        return ia, b * g * u[ia : ia + b.size] / float(fs)
    if output != "displacement":
        raise ValueError(f"output must be 'displacement' or 'velocity', got {output!r}")
    # E = integral of g u x' dt = [g u x] from ts to te - integral of g u' x dt (by parts: the
    # output is never differentiated, u' is the 8th-order central difference of the input)
    idx = np.arange(ia, ia + b.size)
    du = np.zeros(b.size)  # u'_i / fs
    for k, c in enumerate(STENCIL, start=1):
        du += c * (u[idx + k] - u[idx - k])
    w = -g * b * du
    for t, sign in ((te, 1.0), (ts, -1.0)):
        i = int(math.floor(t))
        f = t - i
        if i + 1 - ia >= b.size:  # t on the last sample exactly
            i, f = i - 1, 1.0
        ut = (1.0 - f) * u[i] + f * u[i + 1]
        w[i - ia] += sign * g * ut * (1.0 - f)
        w[i + 1 - ia] += sign * g * ut * f
    return ia, w


def _upward_crossings(x: np.ndarray, hysteresis: float) -> list[float]:
    x = x - np.mean(x)
    h = hysteresis * float(np.std(x))
    out, armed = [], False
    for i in range(1, x.size):
        if x[i - 1] < -h:
            armed = True
        if armed and x[i - 1] < 0.0 <= x[i]:
            out.append(i - 1 + float(-x[i - 1] / (x[i] - x[i - 1])))
            armed = False
    return out


def _steady_from(values, tol: float) -> int:
    """Index where the longest run at the end of ``values`` within ``tol`` (relative) of the median
    of their last half begins (0 for an empty list)."""
    v = np.asarray(values, float)
    if v.size == 0:
        return 0
    ref = float(np.median(v[v.size // 2 :]))
    ok = np.abs(v - ref) <= tol * abs(ref)
    k = v.size
    while k > 0 and ok[k - 1]:
        k -= 1
    return k


def _ptp(x: np.ndarray, ts: float, te: float) -> float:
    seg = x[int(math.ceil(ts)) : int(math.floor(te)) + 1]
    return float(np.ptp(seg)) if seg.size else 0.0


def cycle_bounds(u, fs: float, x_ref) -> dict:
    """Steady cycles of a record: ``{"basis": "drive"|"response", "frequency": Hz or None,
    "bounds": [(ts, te), ...] in fractional samples, "n_cycles": all whole cycles found,
    "steady_from": index of the first steady one}`` (see the module docstring).

    u: the input; x_ref: the displacement the response cycles and the steady test use (the
    predicted mean's).
    """
    u = np.asarray(u, float)
    x_ref = np.asarray(x_ref, float)
    n = u.size
    lo, hi = STENCIL_HALF, n - 2 - STENCIL_HALF  # the stencil of u' reaches STENCIL_HALF past each end
    drive = drive_of(u, fs)
    if drive["kind"] == "sine" and drive["frequency"]:
        f = float(drive["frequency"])
        _, phase, _ = sine_fit(u, fs, f)
        period = fs / f
        k0 = math.ceil(lo / period + phase / (2 * math.pi))
        edges = []
        k = k0
        while True:
            s = (k - phase / (2 * math.pi)) * period
            if s > hi:
                break
            if s >= lo:
                edges.append(s)
            k += 1
        bounds = [(a, b) for a, b in zip(edges[:-1], edges[1:])]
        steady = _steady_from([_ptp(x_ref, a, b) for a, b in bounds], STEADY_TOL)
        return {"basis": "drive", "frequency": f, "bounds": bounds[steady:], "n_cycles": len(bounds),
                "steady_from": steady}
    edges = [s for s in _upward_crossings(x_ref, HYSTERESIS) if lo <= s <= hi]
    bounds = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b - a >= MIN_CYCLE_SAMPLES]
    return {"basis": "response", "frequency": drive["frequency"], "bounds": bounds, "n_cycles": len(bounds),
            "steady_from": 0}


def _extreme(x: np.ndarray, i0: int, i1: int, sign: float) -> float:
    """Fractional index of the max (sign=1) or min (sign=-1) of x over samples i0..i1."""
    seg = sign * x[i0 : i1 + 1]
    k = int(np.argmax(seg))
    if 0 < k < seg.size - 1:
        a, b, c = seg[k - 1 : k + 2]
        den = a - 2 * b + c
        if den < 0:
            return i0 + k + 0.5 * (a - c) / den
    return float(i0 + k)


def _interp(v: np.ndarray, t: float):
    i = min(max(int(math.floor(t)), 0), v.shape[0] - 2)
    f = t - i
    return (1 - f) * v[i] + f * v[i + 1]


def secant_stiffness(x, r, ts: float, te: float) -> float:
    """Secant stiffness (R(x_max) - R(x_min)) / (x_max - x_min) [N/m] of the cycle [ts, te]
    (fractional samples) of a loop (x, R); nan when the cycle does not move."""
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    i0, i1 = int(math.ceil(ts)), int(math.floor(te))
    if i1 - i0 < 2:
        return float("nan")
    tmax, tmin = _extreme(x, i0, i1, 1.0), _extreme(x, i0, i1, -1.0)
    dx = _interp(x, tmax) - _interp(x, tmin)
    return float((_interp(r, tmax) - _interp(r, tmin)) / dx) if dx != 0 else float("nan")


def band_cov(cov_band: np.ndarray, j0: int, m: int) -> np.ndarray:
    """Covariance of samples j0..j0+m-1 from cov_band[i, k] = cov(y_i, y_{i-k}) (0 beyond the band)."""
    L = cov_band.shape[1]
    C = np.zeros((m, m))
    for a in range(m):
        for k in range(min(L, a + 1)):
            C[a, a - k] = C[a - k, a] = cov_band[j0 + a, k]
    return C


def cycles(u, fs: float, physics: dict, mean, *, paths=None, cov_band=None, y=None, confidence: float = 0.99,
           f_highpass: float = 1.0) -> dict:
    """Per-cycle energy and secant stiffness of a free run (see the module docstring).

    u: input record; mean: predicted mean output; paths: Monte Carlo outputs (n x P) or None;
    cov_band: linearised output covariance band (n x L) or None; y: measured output or None.
    physics: ``{"mass", "input_gain", "output"}``. Returns ``{"basis", "frequency", "n_cycles",
    "steady_from", "cycles": [...]}``, each cycle a dict of start/end [s], energy, energy_lower,
    energy_upper [J], stiffness, stiffness_lower, stiffness_upper [N/m] and, with y,
    measured_energy [J] and measured_stiffness [N/m].
    """
    u = np.asarray(u, float)
    mean = np.asarray(mean, float)
    mass, gain = float(physics["mass"]), float(physics.get("input_gain", 1.0))
    output = physics.get("output", "displacement")
    kw = dict(fs=fs, mass=mass, input_gain=gain, output=output, f_highpass=f_highpass)
    x_mean, r_mean = restoring_force(u, mean, **kw)
    info = cycle_bounds(u, fs, x_mean)
    if info["basis"] == "drive" and info["bounds"]:  # start-up: also the mean loop's energy must have settled
        weights = [energy_weights(u, fs, ts, te, gain, output) for ts, te in info["bounds"]]
        k = _steady_from([float(w @ mean[j0 : j0 + w.size]) for j0, w in weights], STEADY_TOL_ENERGY)
        info = {**info, "bounds": info["bounds"][k:], "steady_from": info["steady_from"] + k}
    q_lo, q_hi = (1.0 - confidence) / 2.0, 1.0 - (1.0 - confidence) / 2.0
    z = band_z(confidence)
    meas = None
    if y is not None:
        meas = (np.asarray(y, float),) + restoring_force(u, y, **kw)
    path_loops = None
    if paths is not None and info["bounds"]:
        paths = np.asarray(paths, float)
        path_loops = [restoring_force(u, paths[:, p], **kw) for p in range(paths.shape[1])]
    out = []
    for ts, te in info["bounds"]:
        j0, w = energy_weights(u, fs, ts, te, gain, output)
        sl = slice(j0, j0 + w.size)
        e = float(w @ mean[sl])
        c = {"start": ts / fs, "end": te / fs, "energy": e, "energy_lower": None, "energy_upper": None,
             "stiffness": secant_stiffness(x_mean, r_mean, ts, te), "stiffness_lower": None, "stiffness_upper": None}
        if paths is not None:
            ep = w @ paths[sl]
            c["energy_lower"], c["energy_upper"] = (float(v) for v in np.quantile(ep, [q_lo, q_hi]))
            kp = np.array([secant_stiffness(xp, rp, ts, te) for xp, rp in path_loops])
            kp = kp[np.isfinite(kp)]
            if kp.size:
                c["stiffness_lower"], c["stiffness_upper"] = (float(v) for v in np.quantile(kp, [q_lo, q_hi]))
        elif cov_band is not None:
            cb = np.asarray(cov_band, float)
            sd = math.sqrt(max(float(w @ band_cov(cb, j0, w.size) @ w), 0.0))
            c["energy_lower"], c["energy_upper"] = e - z * sd, e + z * sd
        if meas is not None:
            c["measured_energy"] = float(w @ meas[0][sl])
            c["measured_stiffness"] = secant_stiffness(meas[1], meas[2], ts, te)
        out.append(c)
    return {"basis": info["basis"], "frequency": info["frequency"], "n_cycles": info["n_cycles"],
            "steady_from": info["steady_from"], "cycles": out}


def coverage(cycle_list) -> float | None:
    """Percent of cycles whose measured energy lies inside [energy_lower, energy_upper]."""
    c = [d for d in cycle_list if d.get("measured_energy") is not None and d.get("energy_lower") is not None]
    if not c:
        return None
    return 100.0 * sum(d["energy_lower"] <= d["measured_energy"] <= d["energy_upper"] for d in c) / len(c)


__all__ = ["COV_WINDOW_MAX", "STEADY_TOL", "cov_window_for", "coverage", "cycle_bounds", "cycles", "energy_weights",
           "secant_stiffness"]
