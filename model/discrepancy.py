"""Model-discrepancy term of the free-run band, calibrated on held-out records.

The band of eqs. (8)-(9) propagated in free run (section 2.2, step 3) holds the GP's latent
uncertainty and the noise sigma_y^2. On real records neither covers the model-form error of the
free run: a slightly wrong natural frequency or damping gives an error that grows with the
response (start-up transients, near resonance) while the band stays at the noise floor. This term
adds that error as a variance proportional to the square of the local response amplitude:

    std_total(t)^2 = std(t)^2 + (scale * a(t))^2,    a(t) = RMS of the predicted mean over ``window``
                                                      samples around t [output units]

Where the window lies (``kind``, stored with the scale): ``"centred"`` on t (the window of bundles
calibrated before the choice existed, and their default), or ``"trailing"``, the ``window`` samples
ending at t. A trailing amplitude depends on the mean up to t only, so a record predicted in chunks
(a stream) gets the whole record's band exactly: the state carries the last ``window - 1`` means. A
centred one needs half a window of the future, which a stream's chunk does not have yet. The scale is
calibrated with the kind the band will use, so the trailing window's lag behind a rising amplitude is
covered by the calibration like any other model-form error.

Held amplitude (``hold``, samples; 0: none, the default and the kind of bundles calibrated before
it existed): the amplitude the term scales is a decaying peak-hold of a(t),

    h(t) = max(a(t), h(t - 1) exp(-1 / hold)),

so after a large response (a sweep through resonance, a start-up, the stop of a drive) the band
keeps a share of that response's size for a few time constants. A free run's error outlives the
response that caused it: a lightly damped bolted joint's free decay is the least certain part of
its model (on the real rig the 0.20 V sweep's decay after resonance is 2-3x the model's), while
a(t) follows the model's own, faster decay. h depends on the past only; a stream's state carries
its last value. The scale is calibrated with the hold the band will use.

Propagated-band factor (``gp_scale``, dimensionless; 1: eqs. 8-9's band as propagated, the default and
the factor of bundles calibrated before it existed): the free run's own band is multiplied by it before
the term is added,

    std_total(t)^2 = (gp_scale * std(t))^2 + (scale * h(t))^2.

The propagated band carries sigma_y^2 fed back through every output lag. A single sigma_y^2 is one
number for the whole operating range, so at low response (broadband noise, sines away from resonance, a
free decay) the fed-back noise, amplified by the lightly damped dynamics, can be several times the free
run's actual error, while at high response the amplitude term dominates. Calibrated with the scale
(``calibrate_scale(gp_scales=...)``), the pair is the one whose loosest calibration record is the least
loose (below): neither the quiet records nor the loud ones get a band much wider than they need.

``scale`` is dimensionless (a fraction of the local amplitude). It is calibrated on records the
GP was not trained on (the config's ``lags`` records): the smallest value of a geometric grid at
which every calibration record's band reaches the band's confidence level (the worst record, as
the lag choice), so the band's coverage is a claim checked on held-out data, not a tuned one.
Band edges are widened in quadrature: lower = mean - sqrt((mean - lower)^2 + (z scale a)^2), the
same for the latent band (model-form error is not measurement noise).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpnarx.checks import is_int

from .normal import band_z

#: default averaging window of the local amplitude [s]: several cycles of the rig's resonance
#: (about 19 Hz), one to two of its lowest drive frequencies (5 Hz)
DEFAULT_WINDOW_SECONDS = 0.25
#: where the amplitude window lies: centred on each sample, or ending at it (causal; streams)
WINDOW_KINDS = ("centred", "trailing")
#: the kind of a stored discrepancy that names none (bundles calibrated before the choice existed)
LEGACY_WINDOW_KIND = "centred"
#: the calibration grid of ``scale``: 0 then geometric from 1e-3 to 1 (a band of +/- the amplitude)
SCALE_GRID = np.concatenate([[0.0], np.geomspace(1e-3, 1.0, 61)])
#: the calibration grid of ``gp_scale`` when it is calibrated: geometric from 0.1 to 2 in steps of 10^(1/20)
#: (about 12 %), 1 included
GP_SCALE_GRID = 10.0 ** (np.arange(-20, 7) / 20.0)


def local_amplitude(mean: np.ndarray, window: int, open_end: bool = False, kind: str = "centred") -> np.ndarray:
    """Moving RMS of ``mean`` over ``window`` samples around each sample [output units].

    kind ``"centred"``: the window is centred on each sample; beyond the ends the first and last samples
    repeat. ``open_end``: the record goes on after its last sample (a stream's chunk): a window that
    reaches past the end averages the samples it has instead, the better guess of an amplitude that is
    still to come. kind ``"trailing"``: the ``window`` samples ending at each sample (the first sample
    repeats before the start); it never reaches past the end, so ``open_end`` changes nothing.
    """
    m = np.asarray(mean, dtype=float)
    w = max(1, int(window))
    if kind == "trailing":
        if not m.size:
            return m.copy()
        from numpy.lib.stride_tricks import sliding_window_view

        sq = np.concatenate([np.full(w - 1, m[0] * m[0]), m * m])
        # each window summed on its own (no running sum): a sample's amplitude is the same number
        # whichever chunk of a stream it arrives in
        return np.sqrt(np.maximum(sliding_window_view(sq, w).sum(axis=1) / w, 0.0))
    if kind != "centred":
        raise ValueError(f"window kind must be one of {WINDOW_KINDS}, got {kind!r}")
    if open_end and m.size:
        left, right = w // 2, w - 1 - w // 2  # scipy's centring of an even window
        sq = np.concatenate([np.full(left, m[0] * m[0]), m * m])  # the start repeats, as below
        c = np.concatenate([[0.0], np.cumsum(sq)])
        i = np.arange(m.size)
        hi = np.minimum(i + right, m.size - 1) + left + 1  # exclusive end in sq
        return np.sqrt(np.maximum((c[hi] - c[i]) / (hi - i), 0.0))
    from scipy.ndimage import uniform_filter1d  # here: scipy.ndimage costs 0.2 s of every CLI start

    return np.sqrt(np.maximum(uniform_filter1d(m * m, size=w, mode="nearest"), 0.0))


def held_amplitude(amp: np.ndarray, hold: float, start: float | None = None) -> np.ndarray:
    """Decaying peak-hold of ``amp`` [output units]: h_i = max(amp_i, h_{i-1} exp(-1 / hold)).

    hold: time constant in samples (0: ``amp`` itself). start: h just before the first sample (a
    stream's previous chunk; None or 0: nothing held). Computed in one pass without a loop:
    log h_i = -i / hold + max over j <= i of (log amp_j + j / hold).
    """
    a = np.asarray(amp, dtype=float)
    if not hold or hold <= 0 or a.size == 0:
        return a
    j = np.arange(a.size) / float(hold)
    with np.errstate(divide="ignore"):
        log_a = np.log(np.maximum(a, 0.0)) + j
        if start is not None and start > 0:
            log_a[0] = max(log_a[0], float(np.log(start)) - 1.0 / float(hold))
    return np.exp(np.maximum.accumulate(log_a) - j)


def hold_of(d: dict | None) -> int:
    """The held amplitude's time constant of a stored discrepancy in samples (0 when it names none)."""
    return int((d or {}).get("hold") or 0)


def window_kind(d: dict | None) -> str:
    """The amplitude window's kind of a stored discrepancy (``LEGACY_WINDOW_KIND`` when it names none)."""
    return (d or {}).get("window_kind") or LEGACY_WINDOW_KIND


def check_discrepancy(d: dict | None) -> dict | None:
    """Validate a stored discrepancy (bundle manifest ``band_discrepancy``); None means no term."""
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ValueError(f"band_discrepancy must be an object, got {type(d).__name__}")
    scale, window = d.get("scale"), d.get("window")
    if not isinstance(scale, (int, float)) or not np.isfinite(scale) or not 0.0 <= scale <= 10.0:
        raise ValueError(f"band_discrepancy.scale must be a number in [0, 10], got {scale!r}")
    if not is_int(window, 1):
        raise ValueError(f"band_discrepancy.window must be a positive integer (samples), got {window!r}")
    kind = d.get("window_kind", LEGACY_WINDOW_KIND)
    if kind not in WINDOW_KINDS:
        raise ValueError(f"band_discrepancy.window_kind must be one of {WINDOW_KINDS}, got {kind!r}")
    hold = d.get("hold", 0)
    if not is_int(hold, 0):
        raise ValueError(f"band_discrepancy.hold must be an integer >= 0 (samples), got {hold!r}")
    gp = d.get("gp_scale", 1.0)
    if isinstance(gp, bool) or not isinstance(gp, (int, float)) or not np.isfinite(gp) or not 0.0 < gp <= 10.0:
        raise ValueError(f"band_discrepancy.gp_scale must be a number in (0, 10], got {gp!r}")
    return d


def gp_scale_of(d: dict | None) -> float:
    """The propagated band's factor of a stored discrepancy (1 when it names none)."""
    return float((d or {}).get("gp_scale") or 1.0)


def _widen_pair(mean, lower, upper, extra, gp_scale: float = 1.0):
    lo = mean - np.sqrt((gp_scale * (mean - lower)) ** 2 + extra**2)
    hi = mean + np.sqrt((gp_scale * (upper - mean)) ** 2 + extra**2)
    return lo, hi


def band_amplitude(mean: np.ndarray, window: int, kind: str = "centred", hold: float = 0, mean_before=None,
                   open_end: bool = False, hold_start: float | None = None) -> np.ndarray:
    """The amplitude the discrepancy term scales at each sample of ``mean`` [output units]: the moving RMS
    (``local_amplitude``), held (``held_amplitude``) when ``hold`` > 0. mean_before, hold_start: a stream's
    previous chunk (its last means, its last held value)."""
    before = np.zeros(0) if mean_before is None else np.asarray(mean_before, dtype=float).ravel()
    amp = local_amplitude(np.concatenate([before, np.asarray(mean, dtype=float)]), window, open_end, kind)[before.size:]
    return held_amplitude(amp, hold, hold_start)


def widen(run, scale: float, window: int, mean_before=None, open_end: bool = False, kind: str = "centred",
          hold: float = 0, hold_start: float | None = None, amp: np.ndarray | None = None, gp_scale: float = 1.0):
    """A copy of the free run ``run`` (``freerun.FreeRun``) with the discrepancy term added.

    gp_scale: factor on the run's own band (std, both bands and the latent band) before the term is added
    in quadrature (dimensionless; 1: unchanged). ``cov_band`` is not scaled.
    scale: fraction of the local amplitude (dimensionless); window: samples of the moving RMS; kind:
    where the window lies (``WINDOW_KINDS``); hold: the held amplitude's time constant (samples, 0:
    none). mean_before: the mean outputs just before ``run`` (a stream's earlier chunks; output units):
    the moving RMS of the run's first samples then sees them, as in the run of the whole record;
    hold_start: the held amplitude just before ``run``. open_end: the record goes on after ``run``
    (``local_amplitude``). amp: the amplitude already computed (``band_amplitude``), else computed here.
    """
    g = float(gp_scale)
    if scale <= 0.0 and g == 1.0:
        return run
    if scale <= 0.0:
        extra_sd = np.zeros_like(np.asarray(run.mean, dtype=float))
    else:
        if amp is None:
            amp = band_amplitude(run.mean, window, kind, hold, mean_before, open_end, hold_start)
        extra_sd = float(scale) * amp
    z = band_z(run.confidence)
    lo, hi = _widen_pair(run.mean, run.lower, run.upper, z * extra_sd, g)
    changes = {"std": np.sqrt((g * run.std) ** 2 + extra_sd**2), "lower": lo, "upper": hi}
    if getattr(run, "latent_lower", None) is not None:
        changes["latent_lower"], changes["latent_upper"] = _widen_pair(
            run.mean, run.latent_lower, run.latent_upper, z * extra_sd, g)
    return replace(run, **changes)


def tail_for(kind: str, window: int) -> int:
    """Samples of the mean a stream's state keeps for the next chunk's window: ``window - 1`` for a
    trailing window (all it can see of the past), ``window`` for a centred one."""
    return max(0, int(window) - 1) if kind == "trailing" else int(window)


def widen_chunk(run, disc: dict, mean_before=None, open_end: bool = False, hold_start: float | None = None):
    """(``run`` widened by the stored discrepancy ``disc`` (``band_discrepancy``: scale, window, window_kind,
    hold), the mean outputs the next chunk of a stream needs before it, the held amplitude at the run's
    last sample (None without a hold)). ``mean_before``, ``hold_start``: the previous chunk's such tail
    and held value (None: the record starts with ``run``); ``open_end``: more of the record follows."""
    window, kind, hold = int(disc["window"]), window_kind(disc), hold_of(disc)
    amp = band_amplitude(run.mean, window, kind, hold, mean_before, open_end, hold_start)
    out = widen(run, float(disc["scale"]), window, amp=amp, gp_scale=gp_scale_of(disc))
    prev = np.zeros(0) if mean_before is None else np.asarray(mean_before, dtype=float).ravel()
    both = np.concatenate([prev, np.asarray(run.mean, dtype=float)])
    last = float(amp[-1]) if hold and amp.size else (hold_start if hold else None)
    return out, both[max(0, both.size - tail_for(kind, window)):].copy(), last


def coverage_at(y: np.ndarray, run, scale: float, window: int, skip: int = 0, kind: str = "centred",
                hold: float = 0, amp: np.ndarray | None = None, gp_scale: float = 1.0) -> float:
    """Share of samples of the measured ``y`` inside the band widened by ``scale`` (0-1)."""
    r = widen(run, scale, window, kind=kind, hold=hold, amp=amp, gp_scale=gp_scale)
    y = np.asarray(y, dtype=float)[skip:]
    return float(np.mean((y >= r.lower[skip:]) & (y <= r.upper[skip:])))


def band_tightness(y: np.ndarray, run, skip: int = 0) -> float:
    """How much of its band a record needs: the ``run.confidence`` quantile of |error| / half-width on
    the error's side (dimensionless; <= 1 when the band covers the record at its confidence, 0.5: the band
    is twice as wide as the record needed). A zero half-width counts as 0 where the error is 0, else inf."""
    y = np.asarray(y, dtype=float)[skip:]
    m = np.asarray(run.mean, dtype=float)[skip:]
    e = y - m
    hw = np.where(e >= 0, np.asarray(run.upper, dtype=float)[skip:] - m, m - np.asarray(run.lower, dtype=float)[skip:])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(hw > 0, np.abs(e) / np.where(hw > 0, hw, 1.0), np.where(e == 0, 0.0, np.inf))
    if ratio.size == 0:
        return 0.0
    return float(np.quantile(ratio, run.confidence))


def calibrate_scale(runs, window: int, grid: np.ndarray = SCALE_GRID, kind: str = "centred",
                    hold: int = 0, gp_scales=(1.0,)) -> dict:
    """The smallest ``scale`` of ``grid`` at which every run's band reaches its confidence.

    runs: list of (name, y_measured, FreeRun, skip) for the held-out calibration records; ``skip``
    samples at the start are the measured initial outputs (not predicted) and are not scored.
    kind: where the amplitude window lies (``WINDOW_KINDS``), stored as ``window_kind``; hold: the held
    amplitude's time constant (samples, 0: none), stored as ``hold``.
    gp_scales: the factors on the propagated band to try (``GP_SCALE_GRID`` to calibrate it; the default
    keeps eqs. 8-9's band as propagated). With several, each gets its smallest covering ``scale`` and the
    pair kept is the one whose loosest record is the least loose: the largest smallest
    ``band_tightness`` over the records (ties: the narrower mean band), among the pairs that cover
    every record; none covering, the one with the best worst coverage.
    Returns the ``band_discrepancy`` record: scale, gp_scale, window, window_kind, hold, the target, the
    calibration coverage of each record before and after, each record's tightness after, and ``reached``
    (False when even the largest scale falls short: the largest is then kept and the shortfall is on record).
    """
    if not runs:
        raise ValueError("band calibration needs at least one held-out record")
    if kind not in WINDOW_KINDS:
        raise ValueError(f"window kind must be one of {WINDOW_KINDS}, got {kind!r}")
    hold = int(hold)
    if hold < 0:
        raise ValueError(f"hold must be >= 0 samples, got {hold}")
    factors = [float(g) for g in np.atleast_1d(np.asarray(gp_scales, dtype=float))]
    if not factors or not all(np.isfinite(g) and 0.0 < g <= 10.0 for g in factors):
        raise ValueError(f"gp_scales must be numbers in (0, 10], got {gp_scales!r}")
    target = min(r.confidence for _, _, r, _ in runs)
    amps = {name: band_amplitude(r.mean, window, kind, hold) for name, _, r, _ in runs}  # one per run, any scale

    def coverages(s, g):
        return {name: coverage_at(y, r, s, window, skip, kind, amp=amps[name], gp_scale=g)
                for name, y, r, skip in runs}

    def smallest_scale(g):
        # coverage never falls as the scale grows (the band only widens): bisect the grid
        lo, hi = -1, len(grid) - 1  # grid[hi] is the smallest known to cover (when any does)
        top = coverages(float(grid[hi]), g)
        if min(top.values()) < target:
            return float(grid[hi]), top, False
        best = top
        while hi - lo > 1:
            mid = (lo + hi) // 2
            cov = coverages(float(grid[mid]), g)
            if min(cov.values()) >= target:
                hi, best = mid, cov
            else:
                lo = mid
        return float(grid[hi]), best, True

    def pair_figures(s, g):
        """Each record's ``band_tightness`` and the records' mean band half-width over their std, at (s, g)."""
        tight, widths = {}, []
        for name, y, r, skip in runs:
            w = widen(r, s, window, kind=kind, amp=amps[name], gp_scale=g)
            tight[name] = band_tightness(y, w, skip)
            widths.append(np.mean(w.upper[skip:] - r.mean[skip:]) / max(float(np.std(y[skip:])), 1e-300))
        return tight, float(np.mean(widths))

    before = coverages(0.0, 1.0)
    several = len(factors) > 1
    candidates = []
    for g in factors:
        s, cov, ok = smallest_scale(g)
        tight, width = pair_figures(s, g) if several else ({}, 0.0)
        # covering pairs first, by their loosest record's tightness, then the narrower band; else the best
        # worst coverage
        key = (True, min(tight.values(), default=0.0), -width, min(cov.values())) if ok else \
            (False, min(cov.values()), 0.0, 0.0)
        candidates.append((key, g, s, cov, ok, tight))
    _, g, chosen, after, reached, tight = max(candidates, key=lambda c: c[0])
    out = {"method": "amplitude", "scale": chosen, "gp_scale": g, "window": int(window), "window_kind": kind,
           "hold": hold, "target": float(target), "reached": reached, "criterion": "worst held-out record",
           "coverage_before": before, "coverage_after": after}
    if several:
        out["gp_scale_criterion"] = "largest smallest band_tightness over the records"
        out["tightness_after"] = tight
        out["gp_scale_grid"] = factors
    return out


__all__ = ["DEFAULT_WINDOW_SECONDS", "GP_SCALE_GRID", "LEGACY_WINDOW_KIND", "SCALE_GRID", "WINDOW_KINDS",
           "band_amplitude", "band_tightness", "calibrate_scale", "check_discrepancy", "coverage_at", "gp_scale_of",
           "held_amplitude", "hold_of", "local_amplitude",
           "tail_for", "widen", "widen_chunk", "window_kind"]
