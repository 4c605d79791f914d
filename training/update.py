"""Update a bundle from new healthy records without a full retrain: ``gpnarx update NAME RECORD...``.

``update(bundle, records, registry, config=...)`` runs, in order:

1. **the monitor's judgement** of every new record (when the bundle has a novelty monitor): the record's free run
   from its first ny measured outputs and its score, threshold and verdict as ``gpnarx novelty`` gives them
   (``model.novelty.assess_novelty``; the monitor's own paths and propagation, seed 0). A record judged ``novel`` is
   refused (``NovelRecordError``): updating on damage would teach the monitor to accept it. ``accept_novel``
   overrides, and the lineage says so. Without a monitor the verdict is ``unmonitored``, and the record is taken.
2. **the rank update** (``GPNARX.partial_fit``): the exact posterior conditioned also on a share of the new records'
   rows, hyperparameters, scalers and lags held, within the config's row budget (``max_train_points``): when the
   budget is full, the model's selection rule picks the present rows that stay, which are refactored.
3. **the recalibrations** of the config the bundle was trained from, by the functions training uses: the held-out
   noise (``GPNARX.recalibrate_noise``, ``[model] noise_calibration = "lags"``), the band's discrepancy term
   (``pipeline.calibrate_band_from_config``, ``band_calibration = "lags"``) and the novelty threshold
   (``novelty_calibration.calibration_of`` on the config's ``healthy`` records, when the bundle has a monitor).
4. **a new version**, written atomically like any other (``storage.bundle.save_bundle``), with ``lineage`` in its
   manifest: the parent version, each new record's name, sha256 (u then y as little-endian float64, the audit
   log's rule), samples and verdict, the UTC time, ``accept_novel``, the rows added and dropped and what was
   recalibrated. A server picks it up as any new version (its registry poll or reload).

The version's ``training`` block is the parent's with the new row counts: its per-record metrics are the parent's,
not re-evaluated (``gpnarx validate`` scores a record against the new version). The parent's report is not copied.
The sparse posterior cannot be updated: it needs a retrain (``UpdateError`` says so before any work).
"""
from __future__ import annotations

import copy
import datetime as _dt
import hashlib
import time

import numpy as np

from gpnarx.model.envelope import assess
from gpnarx.model.novelty import assess_novelty, novelty_start
from gpnarx.model.record import FS_RTOL, Record, fs_matches, resample_advice
from gpnarx.storage.bundle import Bundle, save_bundle
from gpnarx.storage.jsonsafe import to_json_safe
from gpnarx.training.config import DatasetConfig
from gpnarx.training.novelty_calibration import calibration_of
from gpnarx.training.pipeline import as_config, calibrate_band_from_config

__all__ = ["NovelRecordError", "UpdateError", "judge_records", "record_sha256", "update"]


class UpdateError(ValueError):
    """An update that cannot be done as asked (the message names the argument or record and the limit)."""


class NovelRecordError(UpdateError):
    """A new record the bundle's novelty monitor judges ``novel`` (refused unless ``accept_novel``)."""


def record_sha256(u, y=None) -> str:
    """SHA-256 of u then y (when given) as little-endian float64 bytes (the audit log's ``record_sha256``)."""
    h = hashlib.sha256(np.ascontiguousarray(np.asarray(u, dtype="<f8")).tobytes())
    if y is not None:
        h.update(np.ascontiguousarray(np.asarray(y, dtype="<f8")).tobytes())
    return h.hexdigest()


def _check_records(bundle: Bundle, records) -> list[Record]:
    records = list(records)
    if not records:
        raise UpdateError("records: at least one new record is needed")
    need = bundle.model.ny + bundle.model.nu + 2
    for rec in records:
        if rec.y is None:
            raise UpdateError(f"{rec.name}: an update record needs its measured output y")
        if not fs_matches(rec.fs, bundle.fs):
            raise UpdateError(f"{rec.name}: fs {rec.fs:.12g} Hz does not match model {bundle.name}:{bundle.version} fs "
                              f"{bundle.fs:.12g} Hz (tolerance {FS_RTOL * 1e6:g} ppm): "
                              f"{resample_advice(rec.fs, bundle.fs)}")
        if rec.n < need:
            raise UpdateError(f"{rec.name}: {rec.n} samples; an update record needs at least {need} "
                              f"(ny={bundle.model.ny}, nu={bundle.model.nu})")
    return records


def judge_records(bundle: Bundle, records) -> list[dict]:
    """Each record's judgement by ``bundle``'s novelty monitor, as ``gpnarx novelty`` scores it: name, sha256,
    samples, verdict (``healthy``, ``novel``, ``unjudged``; ``unmonitored`` when the bundle has no monitor), score
    and threshold."""
    nov = bundle.manifest.get("novelty") if isinstance(bundle.manifest.get("novelty"), dict) else None
    out = []
    for rec in records:
        entry = {"name": rec.name, "sha256": record_sha256(rec.u, rec.y), "n_samples": int(rec.n)}
        if nov is None:
            out.append({**entry, "verdict": "unmonitored"})
            continue
        model = bundle.model
        method = bundle.default_method("novelty")
        paths = int(nov.get("mc_paths") or 0) or 1024
        run = model.simulate(rec.u, n_paths=paths, seed=0, method=method, y0=novelty_start(rec.y, model.ny))
        flags = assess(model.envelope_, run, rec.u, rec.y)
        a = assess_novelty(nov, rec.u, rec.y, bundle.fs, run, start="measured", flags=flags)
        out.append({**entry, "verdict": a["verdict"], "score": a["score"], "threshold": a["threshold"],
                    "out_of_range": a["out_of_range"]})
    return out


def _check_config(cfg: DatasetConfig, bundle: Bundle, records) -> None:
    """The config must be the bundle's: same fs and lags; and no update record may be one of its held-out
    ('lags', 'healthy') records, which the recalibrations score as unseen."""
    model = bundle.model
    if not fs_matches(cfg.fs, bundle.fs):
        raise UpdateError(f"config: {cfg.name} has fs {cfg.fs:g} Hz, the bundle {bundle.fs:g} Hz; give the config "
                          "the bundle was trained from")
    lags = cfg.model.get("ny"), cfg.model.get("nu")
    if isinstance(lags[0], int) and isinstance(lags[1], int) and lags != (model.ny, model.nu):
        raise UpdateError(f"config: {cfg.name} has ny={lags[0]}, nu={lags[1]}, the bundle ny={model.ny}, "
                          f"nu={model.nu}; give the config the bundle was trained from")
    held = {record_sha256(r.u, r.y): r.name for role in ("lags", "healthy") for r in cfg.records_for(role)}
    for rec in records:
        name = held.get(record_sha256(rec.u, rec.y))
        if name is not None:
            raise UpdateError(f"{rec.name}: it is the config's held-out record {name!r}, which the noise, band and "
                              "novelty calibrations score as unseen; it cannot also be a training record")


def update(bundle: Bundle, records, registry, *, config=None, accept_novel: bool = False, version=None,
           name: str | None = None, log=None, now=None) -> dict:
    """Write a new version of ``bundle`` updated from new healthy ``records`` (``model.record.Record`` with y, at
    the bundle's fs) and recalibrated with ``config`` (a ``DatasetConfig`` or path: the config the bundle was
    trained from; None: no recalibration, refused when the bundle has a noise or band calibration). Returns name,
    version, path, lineage and the seconds of each step [s]. ``now``: the lineage's time (a timezone-aware
    datetime; default the present, UTC)."""
    log = log or (lambda msg: None)
    t0 = time.perf_counter()
    seconds = {}
    if bundle.model.posterior_.kind != "exact":
        raise UpdateError(f"model {bundle.name}:{bundle.version} has a {bundle.model.posterior_.kind} posterior, "
                          "which keeps no statistics of its training rows to update: it needs a retrain "
                          "(gpnarx train)")
    records = _check_records(bundle, records)
    m = bundle.manifest
    cfg = as_config(config) if config is not None else None
    needs = [what for what, key in (("noise", "noise_calibration"), ("band", "band_discrepancy")) if m.get(key)]
    if cfg is None and needs:
        raise UpdateError(f"config: model {bundle.name}:{bundle.version} has a {' and a '.join(needs)} calibration "
                          "on held-out records, which an update redoes: give the config it was trained from")
    if cfg is not None:
        _check_config(cfg, bundle, records)

    judged = judge_records(bundle, records)
    seconds["judge"] = time.perf_counter() - t0
    for j in judged:
        log(f"  {j['name']}: {j['verdict']}" + (f" (score {j['score']:.4g}, threshold {j['threshold']:.4g})"
                                                 if "score" in j else ""))
    novel = [j for j in judged if j["verdict"] == "novel"]
    if novel and not accept_novel:
        j = novel[0]
        raise NovelRecordError(
            f"{j['name']}: the novelty monitor of {bundle.name}:{bundle.version} judges it novel (score "
            f"{j['score']:.4g} > threshold {j['threshold']:.4g}); updating on it would teach the monitor to accept it. "
            "Pass --accept-novel (accept_novel=True) only for a record known to come from the healthy structure")

    t = time.perf_counter()
    model = copy.deepcopy(bundle.model)
    model.partial_fit(records)
    up = dict(model.update_)
    seconds["rank_update"] = time.perf_counter() - t
    log(f"rows: {up['rows_added']} added, {up['rows_dropped']} dropped, {up['rows']} in the posterior "
        f"(budget {up['budget']}) in {seconds['rank_update']:.2f} s")

    recal = {"noise": None, "band": None, "novelty": None}
    if cfg is not None and m.get("noise_calibration") and cfg.model.get("noise_calibration", "none") == "lags":
        t = time.perf_counter()
        before = model.noise_var_
        model.recalibrate_noise(cfg.records_for("lags"))
        seconds["noise"] = time.perf_counter() - t
        recal["noise"] = {"noise_var_before": before, "noise_var": model.noise_var_}
        log(f"noise recalibrated: sigma_y^2 {before:.4g} -> {model.noise_var_:.4g} (standardised) in "
            f"{seconds['noise']:.1f} s")
    if cfg is not None and m.get("band_discrepancy") and cfg.model.get("band_calibration", "none") == "lags":
        t = time.perf_counter()
        before = (m["band_discrepancy"] or {}).get("scale")
        d = calibrate_band_from_config(model, cfg, cfg.records_for("lags"), log)
        seconds["band"] = time.perf_counter() - t
        recal["band"] = {"scale_before": before, "scale": d.get("scale"), "gp_scale": d.get("gp_scale")}

    novelty = m.get("novelty") if isinstance(m.get("novelty"), dict) else None
    if novelty is not None:
        healthy = cfg.records_for("healthy") if cfg is not None else []
        if len(healthy) >= 2:
            t = time.perf_counter()
            cal = novelty.get("calibration") or {}
            staged = Bundle(model=model, manifest=m, path=bundle.path)  # the updated model under the parent's monitor
            novelty, _scored = calibration_of(
                staged, healthy, false_alarm_rate=float(novelty.get("false_alarm_rate") or 0.01),
                score_method=novelty.get("method"), n_paths=int(novelty.get("mc_paths") or 1024),
                seed=int(cal.get("seed", 0)), propagation=bundle.default_method("novelty"),
                groups=cal.get("groups") if cal.get("groups") and len(cal["groups"]) == len(healthy) else None)
            seconds["novelty"] = time.perf_counter() - t
            recal["novelty"] = {"threshold_before": m["novelty"].get("threshold"), "threshold": novelty["threshold"],
                                "records": len(healthy)}
            log(f"novelty threshold recalibrated on {len(healthy)} healthy record(s): "
                f"{m['novelty'].get('threshold'):.4g} -> {novelty['threshold']:.4g}")
        else:
            recal["novelty"] = "kept: no healthy records in the config to recalibrate the threshold on"
            log("novelty threshold kept (the config has no healthy records to recalibrate it on)")

    when = (now or _dt.datetime.now(_dt.timezone.utc)).astimezone(_dt.timezone.utc)
    lineage = {
        "parent": {"name": bundle.name, "version": bundle.version, "created": m.get("created")},
        "updated": when.isoformat(timespec="seconds"),
        "accept_novel": bool(accept_novel),
        "records": judged,
        "rows": up,
        "recalibrated": recal,
        "config": None if cfg is None else str(cfg.path),
        "training_metrics": "the parent's, not re-evaluated",
        "ancestors": [*((m.get("lineage") or {}).get("ancestors") or []), bundle.version],
    }
    training = {**(m.get("training") or {}), "n_train": model.n_train_, "n_rows": model.n_rows_}
    t = time.perf_counter()
    path = save_bundle(model, registry, name or bundle.name, version, fs=bundle.fs, units=m.get("units") or {},
                       physics=m.get("physics"), novelty=novelty, training=to_json_safe(training),
                       extra={"predict": m.get("predict"), "lineage": to_json_safe(lineage)})
    seconds["write"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    log(f"written {name or bundle.name}:{path.name} at {path}")
    return {"name": name or bundle.name, "version": path.name, "path": str(path), "parent_version": bundle.version,
            "lineage": to_json_safe(lineage), "seconds": seconds, "model": model}
