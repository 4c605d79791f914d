"""What a model was trained on, and whether an answer lies outside it.

A GP-NARX free run feeds its own predictions back as regressors (eq. 3). Where the input or the
predicted output leaves the region the training regressors cover, eq. (8)'s mean is an
extrapolation of the kernel (eq. 12's cubic term grows as the cube of the regressors) and can run
away; nothing in the mean itself says so. Every answer therefore carries two flags:

* ``out_of_range``: a list naming ``"u"`` when the record's peak |u| exceeds ``RANGE_FACTOR`` times
  the largest training peak |u| (input units, e.g. N or V), ``"y"`` when the measured output's peak
  |y| exceeds ``RANGE_FACTOR`` times the training peak |y| (output units, e.g. m or m/s), and
  ``"prediction"`` when the predicted mean's peak |y| does. Empty when all lie inside.
* ``diverged_paths``: Monte Carlo paths whose sampled output left the training output envelope by
  more than ``DIVERGENCE_FACTOR`` (peak |y_path| > 3 x training peak |y|); the linearised method,
  which has one mean trajectory, reports 0 or 1 by the same rule on its mean.

When either flag is raised the mean, band, fit, RMSE and coverage are still returned (they describe
what the model computed), but they are extrapolations, not predictions the model stands behind.

The envelope is amplitude-only (peak |u|, peak |y| over the training records): an input inside it
at a frequency or waveform the training records never held is not flagged by it; the validation
tables in ``docs/`` say where the shipped models were checked.
"""
from __future__ import annotations

import math

import numpy as np

RANGE_FACTOR = 1.5  # peak |u|, |y| or |mean| beyond 1.5x the training peak -> out_of_range
DIVERGENCE_FACTOR = 3.0  # peak |y| of a path (or the linearised mean) beyond 3x -> diverged
RANGE_FIELDS = ("u", "y", "prediction")


def training_envelope(pairs) -> dict:
    """Peak |u| and peak |y| over training (u, y) pairs, in input and output units.

    Returns ``{"u_peak": float, "y_peak": float, "n_records": int}``.
    """
    pairs = [(np.asarray(u, float), np.asarray(y, float)) for u, y in pairs]
    if not pairs:
        raise ValueError("at least one training record is needed for the training envelope")
    return {"u_peak": max(float(np.max(np.abs(u))) for u, _ in pairs),
            "y_peak": max(float(np.max(np.abs(y))) for _, y in pairs),
            "n_records": len(pairs)}


def check_envelope(env) -> dict | None:
    """``env`` as a validated envelope dict, or None when absent (a model trained without one)."""
    if env is None:
        return None
    try:
        u_peak, y_peak = float(env["u_peak"]), float(env["y_peak"])
    except (KeyError, TypeError, ValueError):
        raise ValueError("training envelope must hold numbers u_peak and y_peak") from None
    if not (math.isfinite(u_peak) and math.isfinite(y_peak) and u_peak >= 0 and y_peak > 0):
        raise ValueError(f"training envelope peaks must be finite, u_peak >= 0 and y_peak > 0; got "
                         f"{u_peak!r}, {y_peak!r}")
    return {**dict(env), "u_peak": u_peak, "y_peak": y_peak}


def divergence_limit(env: dict | None) -> float | None:
    """Peak |y| [output units] beyond which a path counts as diverged (None without an envelope)."""
    return None if env is None else DIVERGENCE_FACTOR * float(env["y_peak"])


def _peak(a) -> float:
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return 0.0
    if not np.all(np.isfinite(a)):
        return math.inf
    return float(np.max(np.abs(a)))


def out_of_range(env: dict | None, u, y=None, mean=None) -> list[str]:
    """Names among ``RANGE_FIELDS`` whose peak lies beyond ``RANGE_FACTOR`` x the training peak.

    u: the record's input; y: its measured output (optional); mean: the predicted mean (optional).
    Non-finite values count as outside. [] without an envelope.
    """
    if env is None:
        return []
    out = []
    if _peak(u) > RANGE_FACTOR * env["u_peak"]:
        out.append("u")
    if y is not None and _peak(y) > RANGE_FACTOR * env["y_peak"]:
        out.append("y")
    if mean is not None and _peak(mean) > RANGE_FACTOR * env["y_peak"]:
        out.append("prediction")
    return out


def assess(env: dict | None, run, u, y=None) -> dict:
    """``{"diverged_paths": int, "out_of_range": [...]}`` for a free run (``model.freerun.FreeRun``).

    A Monte Carlo run counts its own diverged paths (``run.diverged_paths``); a linearised run
    reports 1 when its mean's peak exceeds the divergence limit, else 0.
    """
    limit = divergence_limit(env)
    if limit is None:
        diverged = 0
    elif run.method == "mc":
        diverged = int(getattr(run, "diverged_paths", 0))
    else:
        diverged = int(_peak(run.mean) > limit)
    return {"diverged_paths": diverged, "out_of_range": out_of_range(env, u, y, run.mean)}


__all__ = ["DIVERGENCE_FACTOR", "RANGE_FACTOR", "RANGE_FIELDS", "assess", "check_envelope", "divergence_limit",
           "out_of_range", "training_envelope"]
