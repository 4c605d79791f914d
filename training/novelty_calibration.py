"""Recalibrate a bundle's novelty monitor from new healthy records, without refitting the GP.

``calibrate(bundle, records, registry)`` scores each healthy record exactly as ``gpnarx novelty``
and the service do (free run from the record's first ny measured outputs, the bundle's score
method, ``model.novelty``), fits the threshold for the false-alarm rate (``calibrate_threshold``),
takes the calibration envelope (peak |u|, |y| range) and the probe contract (``model.probe``:
excitation kind, frequency, amplitude range, start rule) from the same records, and writes a new
version of the bundle whose arrays are the source's, byte for byte (``storage.bundle.derive_bundle``).

Why offline only (a CLI command, no HTTP route): the service is read-only over its registry (it
loads versions written by training and never writes them), so a new threshold goes through the same
path as a new model: written atomically as a new version, picked up by the server's registry poll
or reload, and the old version stays servable for comparison and rollback. Calibration also runs
one free run per healthy record, which is training-sized work, not request-sized.
"""
from __future__ import annotations

import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor

from gpnarx.model.novelty import (
    RMS_METHOD,
    calibrate_threshold,
    check_method,
    judge,
    method_of,
    novelty_score,
    novelty_start,
    record_envelope,
)
from gpnarx.model.probe import probe_contract
from gpnarx.model.record import FS_RTOL, fs_matches, resample_advice
from gpnarx.storage.bundle import Bundle, derive_bundle

__all__ = ["calibrate", "calibration_of", "score_healthy"]


def _score_one(bundle: Bundle, rec, k: int, method: str, n_paths: int, seed: int, propagation: str, progress) -> dict:
    """Score of healthy record ``rec`` (the k-th: seed ``seed + k``) by the scoring rule of ``gpnarx novelty``."""
    model = bundle.model
    if rec.y is None:
        raise ValueError(f"{rec.name}: a healthy record needs its measured output y")
    if not fs_matches(rec.fs, bundle.fs):
        raise ValueError(f"{rec.name}: fs {rec.fs:.12g} Hz does not match model {bundle.name}:{bundle.version} fs "
                         f"{bundle.fs:.12g} Hz (tolerance {FS_RTOL * 1e6:g} ppm): {resample_advice(rec.fs, bundle.fs)}")
    y0 = novelty_start(rec.y, model.ny)
    if y0 is None:
        raise ValueError(f"{rec.name}: a healthy record must be longer than ny={model.ny} samples")
    run = model.simulate(rec.u, n_paths=n_paths, seed=seed + k, method=propagation, y0=y0,
                         progress=None if progress is None else progress(rec))
    s = novelty_score(rec.y, run.mean, run.std, method)
    return {"name": rec.name, "score": s["score"], "n_samples": rec.n}


_FORKED: dict = {}  # what the forked scorers of ``score_healthy(jobs > 1)`` inherit


def _forked_score(k: int) -> dict:
    a = _FORKED
    return _score_one(a["bundle"], a["records"][k], k, a["method"], a["n_paths"], a["seed"], a["propagation"], None)


def _sent_score(bundle: Bundle, rec, k: int, method: str, n_paths: int, seed: int, propagation: str) -> dict:
    return _score_one(bundle, rec, k, method, n_paths, seed, propagation, None)


def _fork_is_safe() -> bool:
    """Whether this process may be forked: POSIX, and no JAX loaded (JAX runs threads of its own, a forked
    copy of them may deadlock, and JAX warns on ``os.fork()``)."""
    return "fork" in multiprocessing.get_all_start_methods() and "jax" not in sys.modules


def score_healthy(bundle: Bundle, records, method: str, n_paths: int = 1024, seed: int = 0,
                  propagation: str = "mc", progress=None, jobs: int = 1) -> list[dict]:
    """Novelty score of each record (``model.record.Record`` with y) by the scoring rule of
    ``gpnarx novelty``; record k uses seed ``seed + k``.

    jobs: records scored at once, each in a forked process (POSIX ``fork``), or, where this process must
    not be forked (JAX loaded: its threads) or cannot be, in processes of a fresh interpreter (the bundle
    and records sent to them); with one record, one at a time. The scores are the same as one at a time
    (each record's seed is its own).
    """
    records = list(records)
    for rec in records:  # checked before any work, as one at a time would
        if rec.y is None:
            raise ValueError(f"{rec.name}: a healthy record needs its measured output y")
    jobs = max(1, min(int(jobs), len(records)))
    if jobs > 1 and _fork_is_safe():
        _FORKED.update(bundle=bundle, records=records, method=method, n_paths=n_paths, seed=seed,
                       propagation=propagation)
        try:
            with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork")) as pool:
                return list(pool.map(_forked_score, range(len(records))))
        finally:
            _FORKED.clear()
    if jobs > 1:
        n = len(records)
        context = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context(context)) as pool:
            return list(pool.map(_sent_score, [bundle] * n, records, range(n), [method] * n, [n_paths] * n,
                                 [seed] * n, [propagation] * n))
    return [_score_one(bundle, rec, k, method, n_paths, seed, propagation, progress) for k, rec in enumerate(records)]


def calibration_of(bundle: Bundle, records, *, false_alarm_rate: float = 0.01, score_method: str | None = None,
                   n_paths: int = 1024, seed: int = 0, propagation: str = "mc", progress=None, jobs: int = 1,
                   groups=None) -> tuple[dict, list[dict]]:
    """The novelty calibration of ``bundle``'s model on healthy ``records`` (the manifest's ``novelty`` block:
    threshold, score method, envelope, probe contract, what it was calibrated on) and each record's score and
    verdict under it; nothing is written. ``calibrate`` writes it as a new version, ``gpnarx update`` (training.update)
    recalibrates an updated model with it."""
    records = list(records)
    if len(records) < 2:
        raise ValueError(f"at least 2 healthy records are needed to calibrate, got {len(records)}")
    old = bundle.manifest.get("novelty") if isinstance(bundle.manifest.get("novelty"), dict) else None
    method = check_method(score_method or (method_of(old) if old else RMS_METHOD))
    scored = score_healthy(bundle, records, method, n_paths, seed, propagation, progress, jobs=jobs)
    if groups is not None:
        groups = [str(g) for g in groups]
        if len(groups) != len(records):
            raise ValueError(f"groups must give one label per healthy record, got {len(groups)} for {len(records)}")
    novelty = calibrate_threshold([s["score"] for s in scored], false_alarm_rate, groups=groups)
    novelty["method"] = method
    novelty["mc_paths"] = int(n_paths) if propagation == "mc" else 0
    novelty["envelope"] = record_envelope([(r.u, r.y) for r in records])
    novelty["probe"] = probe_contract([r.u for r in records], bundle.fs, start="measured")
    novelty["calibration"] = {"records": [r.name for r in records], "source_version": bundle.version,
                              "propagation": propagation, "seed": int(seed), "refit": False}
    if groups is not None:
        novelty["calibration"]["groups"] = groups
    for s, r in zip(scored, records):
        s["verdict"] = judge(novelty, s["score"], r.u, r.y, r.fs)["verdict"]
    return novelty, scored


def calibrate(bundle: Bundle, records, registry, *, false_alarm_rate: float = 0.01, score_method: str | None = None,
              n_paths: int = 1024, seed: int = 0, propagation: str = "mc", version=None, progress=None,
              name: str | None = None, jobs: int = 1, groups=None) -> dict:
    """Write a new version of ``bundle`` calibrated on healthy ``records``; returns its name, version,
    path, the novelty calibration and each record's score and verdict under it. ``name``: write it
    under that model name instead (a monitor derived from a model, same GP). ``jobs``: healthy records
    scored at once (``score_healthy``; the same scores). ``groups``: one label per record (the recording
    each window was cut from): the threshold is then the grouped fit of ``calibrate_threshold``, whose
    spread is that of a new recording, not of more windows of the recordings seen."""
    novelty, scored = calibration_of(bundle, records, false_alarm_rate=false_alarm_rate, score_method=score_method,
                                     n_paths=n_paths, seed=seed, propagation=propagation, progress=progress,
                                     jobs=jobs, groups=groups)
    path = derive_bundle(bundle, registry, {"novelty": novelty}, version=version, name=name)
    return {"name": name or bundle.name, "version": path.name, "path": str(path), "source_version": bundle.version,
            "novelty": novelty, "records": scored}
