"""Bolt-loosening novelty score: how far a measured record lies from the model's free-run band.

Score (documented choice): the root-mean-square standardised residual of the measured output y
under the free-run predictive distribution, s = sqrt(mean(((y - mean) / std)^2)), computed over
samples where the predictive std is positive. Why this one: it uses the same Monte Carlo band the
service returns, it is scale free (a healthy record scores ~1 whatever its amplitude), and it
grows smoothly with the mismatch a torque change produces (shifted resonance -> phase and
amplitude residuals), unlike the fraction outside the 99% band, which saturates and is coarse
on short records. The mean negative log predictive density is reported alongside.

Robust variant (``method="segment_median_rms"``, opt-in per bundle): the standardised residuals
are cut into ``SEGMENTS`` (16) contiguous segments and the score is the median of their RMS values.
Real laser-vibrometer records carry isolated spikes and dropouts (the real BERT 8.5 Hz sine holds
measurement bursts that lift the RMS score of a healthy window several-fold). A spike spoils at
most the segments it falls in, and the median ignores up to 7 of 16,
while a torque change raises every segment, so the variant keeps the sensitivity to persistent
change. The method is chosen in the dataset config (``[novelty] method``), stored with the
threshold in the bundle, and every scorer (training, ``gpnarx novelty``, the service) uses the
bundle's method, so scores and thresholds always agree. Bundles without a method use the RMS score.

Initial condition: a record is scored with the free run started from its own first ny measured
outputs (``novelty_start``), unless the caller gives y0. A monitoring record is usually taken in
steady state (e.g. a probe sine), and a run started from rest would add a start-up transient
that is not a change of the structure. Calibration (``training.pipeline``), ``gpnarx novelty`` and
the service's novelty route all use this rule, so scores and thresholds are comparable.

Calibration: scores of healthy records are modelled as log-normal; the threshold is the
(1 - false_alarm_rate) quantile of that fit, and never below the largest healthy score seen
when fewer than 1/false_alarm_rate healthy records are available.

Grouped calibration (``groups``: one label per score, e.g. the recording a window was cut from):
windows of one recording share its drive and mounting, so the free run's model-form error, which
the score measures, is nearly the same in all of them, and between recordings (drive frequencies)
it differs several-fold (real BERT, 0.15 V sines from 5 to 9.75 Hz: median scores 0.08-0.40,
spread within a recording 3-15 % in log). A pooled fit over many windows of few recordings then
measures the within-recording spread and misses the one that decides a new recording's score.
With two or more groups the log score is modelled as a group level plus a window deviation
(one-way random effects, method of moments): mu = mean of the group means, and the threshold is
exp(mu + z sd) with sd^2 = s_between^2 (1 + 1/G) + s_within^2, the spread of a window of a new
recording (G groups; the 1/G term is the uncertainty of mu).

Probe contract: the threshold also holds only for the excitation it was calibrated with. A bundle
calibrated from healthy records states that probe (``novelty["probe"]``: kind, frequency, amplitude
range, start rule; ``model.probe``), and a record whose drive does not match it is reported with
"probe" in ``out_of_range`` and the verdict "unjudged": the score is kept, not compared (``verdict``).

Calibration envelope: the score is only meaningful in the regime the threshold was calibrated in.
A record far outside it (a probe switched off, a sensor gain error, values around 1e30) can make the
predicted band diverge with it and score like a healthy record. So calibration also stores the
range of peak |u| and peak |y| over the healthy records (``record_envelope``), and a record whose
peak |u| or |y| lies outside that range widened ``ENVELOPE_FACTOR`` (2x) each way is reported in
``out_of_range`` and judged "novel" whatever its score, unless its drive does not match the probe
("unjudged", ``verdict``). Bundles calibrated before the
envelope existed have none and skip this check.
"""
from __future__ import annotations

import numpy as np

from .metrics import rms
from .normal import quantile
from .probe import probe_check

STD_FLOOR_REL = 1e-6
RMS_METHOD = "rms_standardised_residual"
SEGMENT_METHOD = "segment_median_rms"
METHODS = (RMS_METHOD, SEGMENT_METHOD)
SEGMENTS = 16  # segments of the robust variant; a record needs at least this many scored samples
ENVELOPE_FACTOR = 2.0  # a record may be 2x smaller or larger (peak) than the healthy ones


def record_envelope(records) -> dict:
    """Peak-amplitude range of healthy (u, y) pairs: ``{"u": [min peak, max peak], "y": [...]}``,
    in the records' input and output units (e.g. V and m/s)."""
    pairs = [(np.asarray(u, float), np.asarray(y, float)) for u, y in records]
    if not pairs:
        raise ValueError("at least one healthy record is needed for the calibration envelope")
    env = {}
    for k, key in enumerate(("u", "y")):
        peaks = [float(np.max(np.abs(p[k]))) for p in pairs]
        env[key] = [min(peaks), max(peaks)]
    return env


def outside_envelope(u, y, envelope: dict | None, factor: float = ENVELOPE_FACTOR) -> list:
    """Names of the fields ("u", "y") whose peak |value| lies outside ``envelope`` widened
    ``factor`` times each way (non-finite values count as outside); [] when envelope is None."""
    if not envelope:
        return []
    out = []
    for key, values in (("u", u), ("y", y)):
        lo_hi = envelope.get(key)
        if values is None or not lo_hi:
            continue
        a = np.asarray(values, float)
        peak = float(np.max(np.abs(a))) if a.size else 0.0
        if not np.isfinite(peak) or peak > factor * float(lo_hi[1]) or peak < float(lo_hi[0]) / factor:
            out.append(key)
    return out


def novelty_start(y, ny: int, y0=None):
    """Initial outputs for scoring record y: y0 when given, else y's first ny samples (a record not
    longer than ny samples starts from rest, returns None)."""
    if y0 is not None and len(y0) > 0:
        return y0
    y = np.asarray(y, float)
    return y[:ny].copy() if y.size > ny else None


def check_method(method) -> str:
    """``method`` if it is a known score method, else a ValueError naming the choices."""
    if method not in METHODS:
        raise ValueError(f"novelty method must be one of {', '.join(METHODS)}, got {method!r}")
    return method


def method_of(novelty: dict | None) -> str:
    """The score method of a bundle's novelty calibration (the RMS score when none is recorded)."""
    return (novelty or {}).get("method") or RMS_METHOD


def novelty_score(y, mean, std, method: str = RMS_METHOD) -> dict:
    """Score of a measured record y against a prediction (mean, std in output units) by ``method``
    (``RMS_METHOD`` or ``SEGMENT_METHOD``, see the module docstring)."""
    check_method(method)
    y = np.asarray(y, float)
    mean = np.asarray(mean, float)
    std = np.asarray(std, float)
    if not (y.shape == mean.shape == std.shape):
        raise ValueError(f"y, mean and std must have the same length, got {y.size}, {mean.size}, {std.size}")
    floor = STD_FLOOR_REL * (float(np.max(std)) or 1.0)
    ok = std > floor
    if not ok.any():
        raise ValueError("predictive std is zero everywhere; cannot score novelty")
    z = (y[ok] - mean[ok]) / std[ok]
    r = rms(z)
    if method == SEGMENT_METHOD:
        if z.size < SEGMENTS:
            raise ValueError(f"the {SEGMENT_METHOD} score needs at least {SEGMENTS} scored samples, got {z.size}")
        score = float(np.median([rms(c) for c in np.array_split(z, SEGMENTS)]))
    else:
        score = r
    # mean of 0.5 log(2 pi s^2) + 0.5 z^2, its z^2 term as 0.5 rms(z)^2: inf only when that exceeds a double
    nlpd = float(np.mean(0.5 * np.log(2 * np.pi * std[ok] ** 2))) + 0.5 * r * r
    return {"score": score, "nlpd": nlpd, "n_samples": int(ok.sum()), "method": method}


def _grouped_log_fit(logs: np.ndarray, groups) -> dict | None:
    """One-way random-effects fit of log scores by group (module docstring, "Grouped calibration"):
    mu, sd of a window of a new group, and the between/within spreads; None with fewer than 2 groups."""
    labels = [str(g) for g in groups]
    if len(labels) != logs.size:
        raise ValueError(f"groups must give one label per healthy score, got {len(labels)} labels for "
                         f"{logs.size} scores")
    names = list(dict.fromkeys(labels))
    if len(names) < 2:
        return None
    members = [logs[[i for i, g in enumerate(labels) if g == name]] for name in names]
    means = np.array([m.mean() for m in members])
    dof = sum(m.size - 1 for m in members)
    within = float(sum(((m - m.mean()) ** 2).sum() for m in members) / dof) if dof > 0 else 0.0
    n_mean = float(np.mean([m.size for m in members]))
    between = max(float(np.var(means, ddof=1)) - within / n_mean, 0.0)
    sd = float(np.sqrt(between * (1.0 + 1.0 / len(names)) + within))
    return {"mu": float(means.mean()), "sd": sd, "n_groups": len(names), "log_std_between": float(np.sqrt(between)),
            "log_std_within": float(np.sqrt(within))}


def calibrate_threshold(healthy_scores, false_alarm_rate: float = 0.01, groups=None) -> dict:
    """Threshold on the score for a target false-alarm rate from healthy-record scores.

    groups: optional label of each score (e.g. the recording a window comes from); with two or more
    distinct labels the log-normal fit is the grouped one of the module docstring and the answer adds
    ``n_groups``, ``log_std_between`` and ``log_std_within``; None: every score an independent draw.
    """
    s = np.asarray(healthy_scores, float)
    if s.size < 2:
        raise ValueError(f"at least 2 healthy records are needed to calibrate, got {s.size}")
    if not 0.0 < false_alarm_rate < 0.5:
        raise ValueError(f"false_alarm_rate must be in (0, 0.5), got {false_alarm_rate}")
    logs = np.log(np.maximum(s, 1e-12))
    grouped = None if groups is None else _grouped_log_fit(logs, groups)
    if grouped is None:
        mu, sd = float(np.mean(logs)), float(np.std(logs, ddof=1))
    else:
        mu, sd = grouped["mu"], grouped["sd"]
    thr = float(np.exp(mu + quantile(1.0 - false_alarm_rate) * sd))
    if s.size < 1.0 / false_alarm_rate:
        thr = max(thr, float(np.max(s)))
    out = {"threshold": thr, "false_alarm_rate": float(false_alarm_rate), "n_healthy": int(s.size),
           "log_mean": mu, "log_std": sd, "healthy_scores": [float(v) for v in s]}
    if grouped is not None:
        out.update({k: grouped[k] for k in ("n_groups", "log_std_between", "log_std_within")})
    return out


VERDICTS = ("healthy", "novel", "unjudged")


def verdict(score: float, threshold: float, out_of_range=(), probe_match: bool | None = None) -> str:
    """The one place a novelty verdict is decided (HTTP, batch, CLI and training reports all call it).

    'unjudged' when ``probe_match`` is False: the drive is not the probe the threshold was calibrated
    for (``model.probe``), so the score measures the model's accuracy at another excitation, not a
    change of the structure; neither healthy nor an alarm. The answer keeps the score, "probe" in
    its out_of_range and the ``probe_reasons``. This comes first: a wrong drive also moves the
    response out of the calibration envelope, which is then no evidence of damage.
    Else 'novel' when the record left the calibration envelope (``out_of_range`` non-empty, see
    ``outside_envelope``) or the score exceeds the threshold; else 'healthy'. ``probe_match`` None
    (a bundle without a probe contract) or True: the envelope and the score decide.
    """
    if probe_match is False:
        return "unjudged"
    if len(out_of_range) > 0:
        return "novel"
    return "novel" if score > threshold else "healthy"


# ------------------------------------------------------------------------------------------ assessment
class UnusableProbeContract(ValueError):
    """The bundle's probe contract (``novelty["probe"]``) cannot be read: a bundle fault, not the record's."""


def judge(novelty: dict, score: float, u, y, fs: float, *, start: str = "measured", flags: dict | None = None,
          check_probe: bool = True) -> dict:
    """Verdict of a scored record under a novelty calibration: ``{"verdict", "out_of_range"}`` plus,
    with ``check_probe``, the probe fields of ``model.probe.probe_check`` (``probe_match``,
    ``probe_reasons``, ``drive``).

    ``out_of_range`` is ``flags["out_of_range"]`` (the training-envelope flags of the run,
    ``model.envelope.assess``), then the calibration envelope's (``outside_envelope``), then "probe"
    when the drive does not match the probe contract. ``check_probe`` False: the probe is not
    consulted (training scores the very records its contract is derived from).
    """
    outside = outside_envelope(u, y, novelty.get("envelope"))
    base = list((flags or {}).get("out_of_range", []))
    flagged = base + [f for f in outside if f not in base]
    probe: dict = {}
    if check_probe:
        try:
            probe = probe_check(u, fs, novelty.get("probe"), start)
        except ValueError as exc:
            raise UnusableProbeContract(str(exc)) from None
        if probe["probe_match"] is False:
            flagged.append("probe")
    return {"verdict": verdict(score, float(novelty["threshold"]), outside, probe.get("probe_match")),
            "out_of_range": flagged, **probe}


def assess_novelty(novelty: dict, u, y, fs: float, run, *, start: str = "measured", flags: dict | None = None) -> dict:
    """The novelty assessment of a measured record (``u``, ``y``) from its free run ``run`` (mean,
    std): score by the bundle's method, threshold, verdict, false-alarm rate, NLPD, out-of-range flags
    and probe fields. The one assessment ``gpnarx novelty`` and the service's novelty answers share.

    ``ValueError`` when the record cannot be scored; ``UnusableProbeContract`` (a ``ValueError``) when
    the bundle's probe contract is malformed.
    """
    s = novelty_score(np.asarray(y, float), run.mean, run.std, method_of(novelty))
    j = judge(novelty, s["score"], u, y, fs, start=start, flags=flags)
    far = novelty.get("false_alarm_rate")
    return {"score": s["score"], "threshold": float(novelty["threshold"]), "verdict": j.pop("verdict"),
            "false_alarm_rate": float(far) if isinstance(far, (int, float)) else None, "nlpd": s["nlpd"],
            "n_samples": s["n_samples"], "score_method": s["method"], **j}
