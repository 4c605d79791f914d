"""Cycles of a stream: the cycles a record sent in chunks has completed so far, each reported once.

``model.cycles`` cuts a whole record: its steady part, cycles of a fitted drive sine, derivatives over the
whole record. None of that is known before the record ends. A stream (a loops call with ``state`` or
``return_state``) cuts cycles by a causal rule instead, and the unfinished cycle's samples travel in the
state token, so the chunks of a record report, together, exactly the cycles that the record sent whole in
one stream call reports:

- Cuts: upward zero crossings of the predicted mean output (displacement or velocity, the model's output),
  at the fractional sample where the line through the two samples crosses zero. A crossing counts only
  after the mean went below -``HYSTERESIS`` (5 %) of its largest magnitude since the previous crossing
  (noise cannot split a cycle), and not before sample ``MARGIN``.
- A cycle runs from one counted crossing to the next and is kept when it lasts ``MIN_CYCLE_SAMPLES`` to
  ``MAX_CYCLE_SAMPLES`` samples (a longer unfinished cycle is given up: no cycle starts at its crossing,
  so what the token carries stays bounded). It is reported by the first call whose samples reach
  ``MARGIN`` past its end (the input stencil of the energy reaches past it).
- Energy, its interval and the measured energy as in ``model.cycles`` (``energy_weights``: the work of the
  drive, linear in the output; the interval from the Monte Carlo paths' energies or the linearised
  covariance band over the cycle). Secant stiffness of the mean loop (and the measured one) with local
  derivatives over the cycle (velocity integrated by the trapezoid rule, accelerations by central
  differences) instead of the whole record's spectral ones; no stiffness interval in a stream.

The carry (``FreeRunState.carry["loops"]``): the counted crossings not yet closed and the samples from
``MARGIN`` before the earliest of them (input, mean, measured output or NaN, and every path or the
covariance band's rows): at most ``MAX_CYCLE_SAMPLES + 2 MARGIN + 2`` samples of ``3 + P`` (Monte Carlo) or
``3 + L`` (linearised, ``STREAM_COV_WINDOW`` lags) numbers, 8 bytes each.
"""
from __future__ import annotations

import math

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.cycles import (
    COV_WINDOW_MAX,
    HYSTERESIS,
    MIN_CYCLE_SAMPLES,
    STENCIL_HALF,
    band_cov,
    energy_weights,
    secant_stiffness,
)
from gpnarx.model.normal import band_z

MARGIN = STENCIL_HALF + 2  # samples a cycle's energy reads before its start and after its end
MAX_CYCLE_SAMPLES = COV_WINDOW_MAX  # the longest cycle a stream reports (the linearised band's lags)
STREAM_COV_WINDOW = COV_WINDOW_MAX  # lags of output covariance a linearised stream keeps for the intervals
_SERIES = ("u", "mean", "y")


def _local_kinematics(u, m, fs: float, mass: float, gain: float, output: str):
    """(x, R) of an output slice with local derivatives (see the module docstring)."""
    if output == "velocity":
        x = np.concatenate([[0.0], np.cumsum(0.5 * (m[1:] + m[:-1]))]) / fs
        acc = np.gradient(m) * fs
    else:
        x = m
        acc = np.zeros_like(m)
        acc[1:-1] = (m[2:] - 2.0 * m[1:-1] + m[:-2]) * fs * fs
    return x, gain * u - mass * acc


def advance(carry: dict | None, u, mean, *, fs: float, physics: dict, y=None, paths=None, cov_band=None,
            confidence: float = 0.99) -> tuple[list, dict]:
    """The cycles completed by this chunk of a stream and the carry for the next.

    carry: the previous chunk's (None: the stream starts here). u, mean, y: the chunk's input, predicted
    mean and measured output (y None: no measured energies); paths: Monte Carlo outputs (n x P) or
    cov_band: the linearised covariance band (n x L). physics: ``mass``, ``input_gain``, ``output``.
    Returns (cycles, carry); each cycle is a dict of the loops answer's cycle fields.
    """
    u = np.asarray(u, float)
    mean = np.asarray(mean, float)
    n = u.size
    yy = np.full(n, np.nan) if y is None else np.asarray(y, float)
    extra = paths if paths is not None else cov_band
    c = _checked(carry or {})
    pos = c["position"]  # global index of this chunk's first sample
    base = c["base"]
    seg = {k: np.concatenate([c[k], v]) for k, v in zip(_SERIES, (u, mean, yy))}
    if extra is not None:
        ex = np.asarray(extra, float)
        old = c["extra"] if "extra" in c else np.zeros((0, ex.shape[1]))
        if old.size and old.shape[1] != ex.shape[1]:
            raise ValueError("state: the loops carry holds another number of paths or covariance lags")
        seg["extra"] = np.concatenate([old.reshape(-1, ex.shape[1]), ex])
    cuts = c["cuts"]  # [i, frac, opens]: crossing between samples i - 1 and i
    armed, peak = c["armed"], c["peak"]
    prev = c.get("last")
    for j in range(n):  # the crossing rule, sample by sample (the same in one call or in many)
        i = pos + j
        v = mean[j]
        if prev is not None:
            peak = max(peak, abs(prev))
            if prev < -HYSTERESIS * peak:
                armed = True
            if armed and prev < 0.0 <= v:
                frac = float(-prev / (v - prev))
                cuts.append([i, frac, i - 1 >= MARGIN])
                armed, peak = False, 0.0
        if cuts and cuts[-1][2] and i - cuts[-1][0] > MAX_CYCLE_SAMPLES:
            cuts[-1][2] = False  # the open cycle is too long: given up
        prev = v
    end = pos + n  # samples of the stream so far
    mass, gain = float(physics["mass"]), float(physics.get("input_gain", 1.0))
    output = physics.get("output", "displacement")
    q = ((1.0 - confidence) / 2.0, 1.0 - (1.0 - confidence) / 2.0)
    z = band_z(confidence)
    out = []
    while len(cuts) >= 2 and cuts[1][0] + MARGIN <= end:
        (i0, f0, opens), (i1, f1, _) = cuts[0], cuts[1]
        cuts.pop(0)
        length = (i1 - i0) + (f1 - f0)
        if not opens or not MIN_CYCLE_SAMPLES <= length <= MAX_CYCLE_SAMPLES:
            continue
        s0 = i0 - 1 - MARGIN  # the slice every call cuts alike, so the numbers agree bit for bit
        sl = slice(s0 - base, i1 + MARGIN - base)
        us, ms, ys = seg["u"][sl], seg["mean"][sl], seg["y"][sl]
        ts, te = (i0 - 1 - s0) + f0, (i1 - 1 - s0) + f1
        j0, w = energy_weights(us, fs, ts, te, gain, output)
        ws = slice(j0, j0 + w.size)
        e = float(w @ ms[ws])
        x, r = _local_kinematics(us, ms, fs, mass, gain, output)
        cyc = {"start": ((i0 - 1) + f0) / fs, "end": ((i1 - 1) + f1) / fs, "energy": e, "energy_lower": None,
               "energy_upper": None, "stiffness": secant_stiffness(x, r, ts, te), "stiffness_lower": None,
               "stiffness_upper": None}
        if paths is not None:
            ep = w @ seg["extra"][sl][ws]
            cyc["energy_lower"], cyc["energy_upper"] = (float(v) for v in np.quantile(ep, q))
        elif cov_band is not None:
            sd = math.sqrt(max(float(w @ band_cov(seg["extra"][sl], j0, w.size) @ w), 0.0))
            cyc["energy_lower"], cyc["energy_upper"] = e - z * sd, e + z * sd
        if np.all(np.isfinite(ys)):
            cyc["measured_energy"] = float(w @ ys[ws])
            xm, rm = _local_kinematics(us, ys, fs, mass, gain, output)
            cyc["measured_stiffness"] = secant_stiffness(xm, rm, ts, te)
        out.append(cyc)
    if cuts and not cuts[0][2] and len(cuts) == 1:
        cuts = []  # a given-up crossing that closes no pending cycle
    keep_from = min([cu[0] - 1 - MARGIN for cu in cuts] + [end - 1 - MARGIN])  # a cut to come reads from here
    cut = max(0, keep_from - base)
    new = {"position": end, "base": base + cut, "cuts": cuts, "armed": armed, "peak": peak,
           "last": float(mean[-1]) if n else prev,
           **{k: seg[k][cut:].copy() for k in _SERIES}}
    if "extra" in seg:
        new["extra"] = seg["extra"][cut:].copy()
    if new["last"] is None:
        new.pop("last")
    return out, new


def _checked(c: dict) -> dict:
    """A carry (``advance``'s own, or a token's: a client may rebuild one) with every value of the type and range
    ``advance`` writes, as numbers and arrays; ValueError naming the carry otherwise."""
    def bad(what):
        return ValueError(f"state: the loops carry is malformed ({what})")

    def integer(v, what):
        if not is_int(v, 0, 1 << 53):
            raise bad(f"{what} must be a non-negative integer")
        return v

    def number(v, what):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise bad(f"{what} must be a finite number")
        return float(v)

    if not isinstance(c, dict):
        raise bad("not an object")
    pos = integer(c.get("position", 0), "position")
    base = integer(c.get("base", pos), "base")
    if base > pos:
        raise bad("base lies after position")
    held = pos - base  # samples carried: from base up to the chunk's first sample
    out = {"position": pos, "base": base}
    for k in (*_SERIES, "extra"):
        if k not in c:
            if k != "extra" and held:
                raise bad(f"{k} is missing")
            out[k] = np.zeros(0) if k != "extra" else None
            continue
        a = np.asarray(c[k], dtype=float)
        if a.ndim != (2 if k == "extra" else 1) or a.shape[0] != held:
            raise bad(f"{k} must hold the {held} samples from base to position")
        if k != "y" and not np.all(np.isfinite(a)):  # y is NaN where no measured output came
            raise bad(f"{k} holds a non-finite number")
        out[k] = a
    if out["extra"] is None:
        out.pop("extra")
    cuts = c.get("cuts", [])
    if not isinstance(cuts, list) or len(cuts) > held + 1:
        raise bad("cuts must be a list of at most one crossing per carried sample")
    out["cuts"] = []
    for x in cuts:
        if not isinstance(x, list) or len(x) != 3 or not isinstance(x[2], bool):
            raise bad("each cut must be [sample, fraction, opens]")
        i, frac = integer(x[0], "a cut's sample"), number(x[1], "a cut's fraction")
        if not base < i <= pos or not 0.0 <= frac <= 1.0:
            raise bad("a cut lies outside the carried samples")
        out["cuts"].append([i, frac, x[2]])
    armed = c.get("armed", False)
    if not isinstance(armed, bool):
        raise bad("armed must be true or false")
    out["armed"], out["peak"] = armed, number(c.get("peak", 0.0), "peak")
    if "last" in c:
        out["last"] = number(c["last"], "last")
    return out


__all__ = ["MARGIN", "MAX_CYCLE_SAMPLES", "STREAM_COV_WINDOW", "advance"]
