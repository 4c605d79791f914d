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

* ``"frequency"`` in ``out_of_range``: the drive holds more than ``FREQUENCY_SHARE`` (10 %) of its
  power in frequency bands where it is stronger than ``FREQUENCY_FACTOR`` (2x) the strongest the
  training inputs ever were in that band. Bands and strengths come from a short-time Fourier
  transform of u (Hann frames of ``FRAME`` = 1024 samples, half overlap; ``BAND_BINS`` = 8 bins
  per band, i.e. 8 Hz at 1024 Hz, about 5.9 Hz at 750 Hz): a band's strength in a frame is the
  root sum of squares of its bins, and the training envelope keeps, per band, the largest strength
  over every frame of every training record (``u_bands``, input units). So a 0-110 Hz drive to a
  model whose inputs reached 40 Hz (or whose 40-110 Hz inputs were a hundred times weaker) says
  so, while a sine anywhere inside the trained band and level does not. The rule works in
  samples, so it needs no fs; a bundle trained before it existed has no ``u_bands`` and is not
  checked for it.

The peak and band envelopes are what the model saw, not what it predicts well: the validation
tables in ``docs/`` say where the shipped models were checked.
"""
from __future__ import annotations

import math

import numpy as np

RANGE_FACTOR = 1.5  # peak |u|, |y| or |mean| beyond 1.5x the training peak -> out_of_range
DIVERGENCE_FACTOR = 3.0  # peak |y| of a path (or the linearised mean) beyond 3x -> diverged
RANGE_FIELDS = ("u", "y", "prediction", "frequency")
FRAME = 1024  # samples per STFT frame of the frequency check (Hann window, half overlap)
BAND_BINS = 8  # STFT bins per band of the frequency check
FREQUENCY_FACTOR = 2.0  # a band is beyond the training inputs when stronger than 2x their strongest
FREQUENCY_SHARE = 0.10  # "frequency" when more than 10 % of the drive's power lies in such bands


def band_strengths(u) -> np.ndarray:
    """Per-frame band strengths of input ``u``: shape (n_bands, n_frames), input units.

    Short-time Fourier transform (Hann frames of ``FRAME`` samples, half overlap, zero-padded
    ends); a band is ``BAND_BINS`` adjacent bins and its strength is the root sum of squares of
    their magnitudes (scipy's spectrum scaling: a full-frame sine of amplitude A gives about A/2).
    """
    u = np.asarray(u, dtype=float)
    if u.size < FRAME:  # a short record is one zero-padded frame
        u = np.pad(u, (0, FRAME - u.size))
    z = _stft(u)
    p = np.abs(z) ** 2
    n_bands = -(-p.shape[0] // BAND_BINS)
    pad = n_bands * BAND_BINS - p.shape[0]
    p = np.pad(p, ((0, pad), (0, 0)))
    return np.sqrt(p.reshape(n_bands, BAND_BINS, -1).sum(axis=1))


def _stft(u: np.ndarray) -> np.ndarray:
    """``scipy.signal.stft(u, nperseg=FRAME, noverlap=FRAME // 2, window="hann", detrend=False)``'s
    spectrum, shape (FRAME // 2 + 1, frames), by numpy's FFT: half a frame of zeros at each end, zeros up to
    a whole number of hops, periodic Hann frames, each frame's rfft over the window's sum. scipy.signal
    itself (with scipy.stats, which it imports) costs every ``gpnarx predict`` half a second of start-up.
    """
    half = FRAME // 2
    x = np.pad(u, (half, half))
    x = np.pad(x, (0, (-(x.size - FRAME) % half) % FRAME))
    win = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(FRAME) / FRAME)
    frames = np.lib.stride_tricks.sliding_window_view(x, FRAME)[::half] * win
    return (np.fft.rfft(frames, axis=1) / win.sum()).T


def band_envelope(inputs) -> list[float]:
    """Largest band strength over every frame of every input in ``inputs`` (``u_bands``), input units."""
    return [float(v) for v in np.max(np.concatenate([band_strengths(u) for u in inputs], axis=1), axis=1)]


def frequency_share(u_bands, u) -> float:
    """Share (0-1) of ``u``'s STFT power in bands stronger than ``FREQUENCY_FACTOR`` x ``u_bands``."""
    s = band_strengths(u)
    env = np.asarray(u_bands, dtype=float)[:, None]
    power = s * s
    total = float(power.sum())
    if not np.isfinite(total) or total <= 0.0:
        return 0.0
    return float(power[s > FREQUENCY_FACTOR * env].sum() / total)


def training_envelope(pairs) -> dict:
    """Peak |u| and peak |y| over training (u, y) pairs, in input and output units.

    Returns ``{"u_peak": float, "y_peak": float, "n_records": int, "u_bands": [float, ...]}``
    (``u_bands``: the inputs' band envelope, ``band_envelope``).
    """
    pairs = [(np.asarray(u, float), np.asarray(y, float)) for u, y in pairs]
    if not pairs:
        raise ValueError("at least one training record is needed for the training envelope")
    return {"u_peak": max(float(np.max(np.abs(u))) for u, _ in pairs),
            "y_peak": max(float(np.max(np.abs(y))) for _, y in pairs),
            "n_records": len(pairs), "u_bands": band_envelope([u for u, _ in pairs])}


def extend_envelope(env: dict | None, pairs) -> dict | None:
    """The training envelope ``env`` grown to cover more training (u, y) pairs (``GPNARX.partial_fit``): the
    larger peaks, the records counted, each band's larger strength (``u_bands`` only where ``env`` has them).
    None stays None (a model trained without an envelope is not range-checked)."""
    if env is None:
        return None
    new = training_envelope(pairs)
    out = {**env, "u_peak": max(float(env["u_peak"]), new["u_peak"]),
           "y_peak": max(float(env["y_peak"]), new["y_peak"]),
           "n_records": int(env.get("n_records") or 0) + new["n_records"]}
    if env.get("u_bands") is not None:
        out["u_bands"] = [max(float(a), b) for a, b in zip(env["u_bands"], new["u_bands"])]
    return out


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
    out = {**dict(env), "u_peak": u_peak, "y_peak": y_peak}
    if env.get("u_bands") is not None:
        bands = env["u_bands"]
        n_bands = -(-(FRAME // 2 + 1) // BAND_BINS)
        try:
            arr = np.asarray(bands, dtype=float)
        except (TypeError, ValueError):
            raise ValueError("training envelope u_bands must be a list of numbers") from None
        if arr.shape != (n_bands,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ValueError(f"training envelope u_bands must hold {n_bands} finite non-negative numbers")
        out["u_bands"] = [float(v) for v in arr]
    return out


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
    ``"frequency"`` comes after them when the envelope holds ``u_bands`` and more than
    ``FREQUENCY_SHARE`` of u's power lies beyond them (``frequency_share``).
    Non-finite values count as outside. [] without an envelope.
    """
    if env is None:
        return []
    out = []
    peak_u = _peak(u)
    if peak_u > RANGE_FACTOR * env["u_peak"]:
        out.append("u")
    if y is not None and _peak(y) > RANGE_FACTOR * env["y_peak"]:
        out.append("y")
    if mean is not None and _peak(mean) > RANGE_FACTOR * env["y_peak"]:
        out.append("prediction")
    bands = env.get("u_bands")
    if bands is not None and math.isfinite(peak_u) and frequency_share(bands, u) > FREQUENCY_SHARE:
        out.append("frequency")
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


__all__ = ["BAND_BINS", "DIVERGENCE_FACTOR", "FRAME", "FREQUENCY_FACTOR", "FREQUENCY_SHARE", "RANGE_FACTOR",
           "RANGE_FIELDS", "assess", "band_envelope", "band_strengths", "check_envelope", "divergence_limit",
           "extend_envelope", "frequency_share", "out_of_range", "training_envelope"]
