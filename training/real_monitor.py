"""The real-rig novelty monitor ``bert-real-monitor``: the real-BERT model with a novelty calibration.

It is not a second GP: it is ``bert-real`` (same arrays, checked byte for byte) with a novelty
threshold and probe contract from healthy windows of two real recordings, written with the product's
own ``calibrate`` (``derive_bundle``, no refit). The split is fixed here so that the default build,
``gpnarx calibrate`` by hand and the false-alarm study (``training.real_monitor_study``) use the same
one:

- calibration: ``WINDOW_SECONDS`` windows of the steady part (24-48 s) of the 8 Hz and 9.5 Hz
  recordings. The GP trained on 20-22 s of these recordings, which the windows do not overlap;
- false-alarm test (the study only): every window of 6-50 s of the 8.5 Hz and 9 Hz recordings,
  which neither the GP nor the calibration saw.

The score is ``segment_median_rms`` (spike-robust for laser records); free runs start from the
measured outputs (the novelty rule).
"""
from __future__ import annotations

import os
from pathlib import Path

from gpnarx.model.record import Record
from gpnarx.storage.record_files import read_record
from gpnarx.storage.registry import Registry
from gpnarx.training.novelty_calibration import calibrate

SOURCE_MODEL = "bert-real"
MONITOR_NAME = "bert-real-monitor"
#: recording (folder under Sine/) -> steady span [s] whose windows calibrate the threshold
CALIBRATION = {"Sine_08Hz": (24.0, 48.0), "Sine_09p5Hz": (24.0, 48.0)}
#: recording -> span [s] of the false-alarm test windows (never used by the calibration or the GP)
TEST = {"Sine_08p5Hz": (6.0, 50.0), "Sine_09Hz": (6.0, 50.0)}
#: a drive outside the probe contract: its windows must come back flagged "probe"
OFF_PROBE = {"Sine_17Hz": (6.0, 14.0)}
WINDOW_SECONDS = 2.0
SCORE_METHOD = "segment_median_rms"
FALSE_ALARM_RATE = 0.01


def windows(data, spec: dict, width: float = WINDOW_SECONDS) -> list[Record]:
    """Consecutive ``width``-second windows [s] of each recording's span in ``spec``, in order."""
    out = []
    for name, (t0, t1) in spec.items():
        rec = read_record(Path(data) / "Sine" / name)
        t = t0
        while t + width <= t1 + 1e-9:
            w = rec.window(t, t + width)
            w.name = f"{name}_{t:05.1f}s"
            out.append(w)
            t += width
    return out


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def build_real_monitor(root, data, *, mc_paths: int = 256, log=None, jobs: int | None = None) -> dict:
    """Derive ``bert-real-monitor`` from the newest ``bert-real`` in the registry ``root``.

    data: the BERT records folder (``config.bert_data_dir()``); mc_paths: Monte Carlo paths of each
    calibration score; jobs: windows scored at once (default: the cores this process may use; the
    scores do not depend on it). Returns ``calibrate``'s answer (name, version, threshold, scores).
    """
    log = log or (lambda msg: None)
    reg = Registry(root).scan()
    if SOURCE_MODEL not in reg.bundles:
        raise ValueError(f"{MONITOR_NAME} is derived from {SOURCE_MODEL}, which is not in {root}: build it first")
    source = reg.get(SOURCE_MODEL)
    cal = windows(data, CALIBRATION)
    log(f"calibrating {MONITOR_NAME} from {SOURCE_MODEL}:{source.version} on {len(cal)} healthy "
        f"{WINDOW_SECONDS:g} s windows ({', '.join(CALIBRATION)}), {mc_paths} paths each, "
        f"{_cores() if jobs is None else jobs} at a time")
    res = calibrate(source, cal, Path(root), false_alarm_rate=FALSE_ALARM_RATE, score_method=SCORE_METHOD,
                    n_paths=mc_paths, name=MONITOR_NAME, jobs=_cores() if jobs is None else jobs)
    log(f"{MONITOR_NAME}:{res['version']} threshold {res['novelty']['threshold']:.3g}")
    return res


__all__ = ["CALIBRATION", "MONITOR_NAME", "OFF_PROBE", "SOURCE_MODEL", "TEST", "WINDOW_SECONDS", "build_real_monitor",
           "windows"]
