"""Between the recorded frequencies: the model's steady sine response against the rig's own FRF.

The shared real subset holds steady sines at 5-9.75, 17, 19 and 20 Hz only, so a user who drives the
rig at 12 Hz or 25 Hz asks the model about a frequency no sine record shows. The LMS export of the
noise run holds the rig's frequency response (``Rand/*/FRF.mat``: ``FRF_Laser__X_Shaker__X``, free-end
velocity per shaker volt [(m/s)/V], 0.0625 Hz steps, estimated by Test.Lab from the 0.25 V white-noise
run). For each frequency of ``FREQUENCIES`` (none of them a recorded sine) a sine of ``AMPLITUDE`` V,
ramped in over ``RAMP`` s, is free-run from rest with the linearised method for ``SECONDS`` s; the
amplitude of the mean's component at the drive frequency over the last ``FIT_SECONDS`` s (a least-squares
sine fit) is compared with |H(f)| x the drive amplitude. The same comparison on the recorded sines (their
measured output and their own drive) says how well the FRF describes a 0.15 V sine in the first place.

Near the first resonance (``RESONANCE_BAND``, 17-20 Hz) the response depends on the amplitude (the joint
softens and the peak moves), so the noise run's FRF is no reference there and those frequencies are left
out. The noise run's first 10 s are training data of the shipped model: this checks that the model's
response between the recorded sines is the rig's, not that the FRF was unseen.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io as sio

from gpnarx.model.probe import drive_of, sine_fit
from gpnarx.storage.record_files import read_record

AMPLITUDE = 0.15  # V: the level of the recorded sines (0.15 V nominal)
FREQUENCIES = (3.0, 4.0, 7.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0, 22.0, 23.0, 25.0, 28.0, 30.0)  # Hz
RESONANCE_BAND = (16.5, 20.5)  # Hz: amplitude-dependent there; the noise run's FRF is no reference
RAMP = 0.5  # s: the drive's amplitude ramps in linearly, as a shaker's does
SECONDS = 8.0  # s of free run per frequency
FIT_SECONDS = 2.0  # s at the end of the run whose drive-frequency component is compared
RECORDED_WINDOW = (30.0, 32.0)  # s: steady state of a recorded 64 s sine
FRF_VARIABLE = "FRF_Laser__X_Shaker__X"


def find_frf(data_dir) -> Path | None:
    """The reference FRF: the LMS ``FRF.mat`` of the noise run under ``data_dir`` (``Rand/*/FRF.mat``)
    with the strongest drive (largest RMS shaker voltage of its ``TimeShaker.mat``), or None.

    The rig is nonlinear, so noise runs at different levels give different FRFs (the 0.10 V run's
    differs from the 0.25 V run's by several % below 5 Hz); the strongest run is the one closest to
    the level of the 0.15 V sines this check sets the model against. A noise run without its time
    records ranks last.
    """
    hits = sorted(Path(data_dir).glob("Rand/*/FRF.mat"))
    if not hits:
        return None

    def level(frf_path: Path) -> float:
        try:
            return float(np.sqrt(np.mean(read_record(frf_path.parent).u ** 2)))
        except Exception:  # noqa: BLE001 - a run without readable time records cannot be ranked
            return -1.0

    return max(hits, key=level)


def read_lms_frf(path) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies [Hz], complex FRF) of an LMS Test.Lab ``FRF.mat`` export (velocity per volt, (m/s)/V)."""
    try:
        d = sio.loadmat(str(path), squeeze_me=True, struct_as_record=False)
        frf = d[FRF_VARIABLE]
        x = frf.x_values
        h = np.asarray(frf.y_values.values, dtype=complex).ravel()
        f = float(x.start_value) + float(x.increment) * np.arange(int(x.number_of_values))
    except (KeyError, AttributeError, ValueError, OSError) as exc:
        raise ValueError(f"{path}: not an LMS FRF export with {FRF_VARIABLE} ({type(exc).__name__}: {exc})") from None
    if f.size != h.size or f.size < 2:
        raise ValueError(f"{path}: {FRF_VARIABLE} holds {h.size} values for {f.size} frequencies")
    return f, h


def sweep_receptances(data_dir) -> list[dict]:
    """The receptance FRFs of the swept-sine runs under ``data_dir`` (``Chirp/*/*/FRF.mat``), the paper's
    Fig. 12(a): for each run its name, the frequencies [Hz], |H_d| = |H_v| / (2 pi f) [m/V] (displacement
    per volt from the exported velocity per volt; 0 Hz left out) and the peak of |H_d| over 5-40 Hz
    (``peak_freq`` [Hz], ``peak`` [m/V]): the peak moves down as the drive grows (softening). Sorted by
    the run's RMS shaker voltage; [] when there are no such exports."""
    out = []
    for path in sorted(Path(data_dir).glob("Chirp/*/*/FRF.mat")):
        f, h = read_lms_frf(path)
        keep = f > 0
        f, rec = f[keep], np.abs(h[keep]) / (2.0 * np.pi * f[keep])
        band = (f >= 5.0) & (f <= 40.0)
        k = int(np.argmax(np.where(band, rec, -np.inf)))
        try:
            level = float(np.sqrt(np.mean(read_record(path.parent).u ** 2)))
        except Exception:  # noqa: BLE001 - an FRF export without its time records still plots
            level = float("nan")
        out.append({"name": path.parent.name, "freq": f, "receptance": rec, "peak_freq": float(f[k]),
                    "peak": float(rec[k]), "u_rms": level})
    return sorted(out, key=lambda r: (np.isnan(r["u_rms"]), r["u_rms"]))


def frf_gain(f: np.ndarray, h: np.ndarray, freq: float) -> float:
    """|H| at ``freq`` [Hz], linearly interpolated between the FRF's lines."""
    return float(np.interp(freq, f, np.abs(h)))


def drive(freq: float, amplitude: float, fs: float, seconds: float) -> np.ndarray:
    """A sine of ``amplitude`` [V] at ``freq`` [Hz], ramped in over ``RAMP`` s, ``seconds`` long at ``fs``."""
    t = np.arange(int(round(seconds * fs))) / fs
    return amplitude * np.minimum(1.0, t / RAMP) * np.sin(2 * np.pi * freq * t)


def _in_resonance(freq: float) -> bool:
    return RESONANCE_BAND[0] <= freq <= RESONANCE_BAND[1]


def frf_check(model, data_dir, *, fs: float, freqs=FREQUENCIES, amplitude: float = AMPLITUDE,
              seconds: float = SECONDS, recorded=()) -> dict | None:
    """Compare the model's steady sine amplitude with the rig's FRF (see the module docstring).

    model: a fitted ``GPNARX`` of the rig (u in V, y in m/s) at the records' sampling frequency ``fs``
    [Hz]. recorded: record folders whose measured steady amplitude is compared with the FRF too (the
    reference's own accuracy). Amplitudes and drive frequencies come from ``model.probe``
    (``sine_fit``, ``drive_of``), as the novelty probe contract measures them.
    Returns ``{"frf": path, "amplitude": V, "rows": [...], "recorded": [...], "worst_ratio_error": ...}``
    (ratios model / FRF), or None when no FRF export is under ``data_dir``.
    """
    path = find_frf(data_dir)
    if path is None:
        return None
    f, h = read_lms_frf(path)
    n_fit = int(round(FIT_SECONDS * fs))
    rows = []
    for freq in freqs:
        if _in_resonance(freq):
            continue
        run = model.simulate(drive(freq, amplitude, fs, seconds), method="linear")
        got = sine_fit(run.mean[-n_fit:], fs, freq)[0]
        ref = frf_gain(f, h, freq) * amplitude
        half = float(np.mean(run.upper[-n_fit:] - run.lower[-n_fit:]) / 2.0)
        rows.append({"freq": float(freq), "model": got, "frf": ref, "ratio": got / ref, "band_halfwidth": half})
    rec_rows = []
    for folder in recorded:
        rec = read_record(folder)
        i0, i1 = (int(round(s * rec.fs)) for s in RECORDED_WINDOW)
        u, y = rec.u[i0:i1], rec.y[i0:i1]
        d = drive_of(u, rec.fs)
        freq, drive_amp = d["frequency"], d["amplitude"]
        if d["kind"] != "sine" or _in_resonance(freq):
            continue
        got = sine_fit(y, rec.fs, freq)[0]
        ref = frf_gain(f, h, freq) * drive_amp
        rec_rows.append({"record": Path(folder).name, "freq": freq, "drive": drive_amp, "measured": got, "frf": ref,
                         "ratio": got / ref})
    worst = max((abs(r["ratio"] - 1.0) for r in rows), default=None)
    worst_rec = max((abs(r["ratio"] - 1.0) for r in rec_rows), default=None)
    return {"frf": str(path), "amplitude": float(amplitude), "seconds": float(seconds), "rows": rows,
            "recorded": rec_rows, "worst_ratio_error": worst, "worst_recorded_ratio_error": worst_rec}


def markdown(check: dict) -> str:
    """The comparison as Markdown (a section of docs/results-bert-real.md)."""
    amp = check["amplitude"]
    lines = [f"| drive [Hz] | model: steady amplitude [m/s] | rig FRF x {amp:g} V [m/s] | model / FRF | "
             "99 % band half-width [m/s] |", "|---|---|---|---|---|"]
    for r in check["rows"]:
        lines.append(f"| {r['freq']:g} | {r['model']:.4f} | {r['frf']:.4f} | {r['ratio']:.3f} | "
                     f"{r['band_halfwidth']:.4f} |")
    out = "\n".join(lines) + "\n"
    if check["recorded"]:
        out += ("\nThe reference itself, on the recorded sines (steady window 30-32 s, each record's own drive "
                "amplitude):\n\n| record | drive [Hz] | drive [V] | measured [m/s] | FRF x drive [m/s] | "
                "measured / FRF |\n|---|---|---|---|---|---|\n")
        for r in check["recorded"]:
            out += (f"| {r['record']} | {r['freq']:.2f} | {r['drive']:.3f} | {r['measured']:.4f} | {r['frf']:.4f} | "
                    f"{r['ratio']:.3f} |\n")
    worst = check["worst_ratio_error"]
    out += (f"\nLargest departure of the model from the FRF off resonance: {100 * worst:.1f} %"
            + (f" (the FRF against the recorded sines: {100 * check['worst_recorded_ratio_error']:.1f} %)."
               if check["worst_recorded_ratio_error"] is not None else ".") + "\n")
    return out
