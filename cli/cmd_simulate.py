"""``gpnarx simulate``: write a simulated input/output record (u, y, fs).

::

    gpnarx simulate bouc-wen|bert-standin --excitation sweep|sine|multisine|noise --amplitude A
        [--f0 HZ --f1 HZ --rate HZ_PER_S --freq HZ --duration S --seed N --torque NM --scatter K]
        [--noise-fraction F] --out FILE

The record file holds 1-D float64 arrays ``u`` and ``y`` and a scalar ``fs`` [Hz] (``.npz``), or
the columns ``time,u,y`` (``.csv``). Other extensions are accepted when the shared record writer
``storage.record_files.write_record`` supports them.

Systems (defaults follow the paper's protocol, sections 3 and 4):

- ``bouc-wen``: Noel & Schoukens benchmark (``training.simulators.boucwen``), fs = 750 Hz,
  u = force [N], y = displacement [m].
- ``bert-standin``: the documented single-mode hysteretic *stand-in* for the BERT rig
  (``training.simulators.bert_standin``; never the rig's numbers), fs = 1024 Hz, u = shaker
  voltage [V], y = free-end velocity [m/s]. ``--torque`` [N m] (default 5) and ``--seed`` select
  the tightening torque and the realization; ``--scatter`` (default 1) multiplies the realization
  scatter of the stand-in's parameters (e.g. 10 to study larger day-to-day drift; see the simulator).

Excitations (``--amplitude`` is the *peak* for sweep and sine, the *RMS* for multisine and noise):

- ``sweep``: linear swept sine whose frequency is ``f0 + rate * t`` until it reaches ``f1``.
  The record lasts ``--duration`` (default: Bouc-Wen, exactly the sweep, (150 - 5) / 53 = 2.74 s,
  2052 samples; BERT stand-in, 16 s = 16384 samples: the 0-40 Hz sweep at 5 Hz/s takes 8 s and
  is followed by 8 s of zero input, a 50 % burst). A shorter ``--duration`` truncates the sweep, a
  longer one appends zero input. Starts from rest.
- ``sine``: ``A sin(2 pi freq t)`` (default 35.59 Hz, the Bouc-Wen linear resonance, for 2 s;
  BERT stand-in 18 Hz for 16 s). Returned in steady state: the system is run from rest over a
  pre-roll of the same sine (Bouc-Wen 8 s, BERT stand-in 10 s) and a short tail (0.25 s) that
  are cut off, so the returned record starts at phase 0.
- ``multisine``: random-phase multisine (``training.excitations.multisine``), one period of
  ``--duration * fs`` samples (default 8192 samples, as the benchmark: 10.92 s at 750 Hz; BERT
  stand-in 16384 samples), band 5-150 Hz (BERT stand-in 0-40 Hz), returned in periodic steady
  state (Bouc-Wen: periodic simulation; stand-in: two periods from rest, the last kept).
- ``noise``: Gaussian noise band-limited to [f0, f1] (Bouc-Wen 5-150 Hz for 8192 samples; BERT
  stand-in 0-110 Hz for 16 s, like the paper's white-noise validation), starts from rest.

``--noise-fraction F`` adds Gaussian output noise of variance ``F * mean(y**2)`` (F = 0.1 is
"10 % of the response energy"), seeded by ``--seed`` on a stream separate from the excitation's.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from gpnarx.cli.errors import CLIError, UsageError
from gpnarx.model.record import Record
from gpnarx.storage.atomicio import atomic_file
from gpnarx.storage.record_files import write_record
from gpnarx.training.simulation_specs import (
    DEFAULTS,
    EXCITATIONS,
    SYSTEMS,
    USES,
    excitation,
    padded_sine,
    sine_padding,
)

PROGRESS_ABOVE = 10.0  # s of simulated signal above which a progress bar is shown (on a TTY)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a record (u, y, fs) of the Bouc-Wen benchmark or the BERT stand-in",
        description=__doc__.split("\n\n")[0],
    )
    # Values are parsed and checked in run() so that a bad value is one line on stderr + exit 2.
    p.add_argument("system", nargs="?", metavar="SYSTEM", help="bouc-wen or bert-standin")
    p.add_argument("--excitation", default="sweep", metavar="KIND", help="sweep (default), sine, multisine or noise")
    p.add_argument("--amplitude", metavar="A", help="peak (sweep, sine) or RMS (multisine, noise) in N or V")
    p.add_argument("--f0", metavar="HZ", help="band start [Hz]")
    p.add_argument("--f1", metavar="HZ", help="band end [Hz]")
    p.add_argument("--rate", metavar="HZ_PER_S", help="sweep rate [Hz/s]")
    p.add_argument("--freq", metavar="HZ", help="sine frequency [Hz]")
    p.add_argument("--duration", metavar="S", help="record (or multisine period) length [s]")
    p.add_argument("--seed", metavar="N", help="random seed (multisine phases, noise, stand-in realization)")
    p.add_argument("--torque", metavar="NM", help="BERT stand-in tightening torque [N m] (default 5)")
    p.add_argument("--scatter", metavar="K", help="BERT stand-in realization scatter multiplier, 0-100 (default 1)")
    p.add_argument("--noise-fraction", dest="noise_fraction", metavar="F", help="output noise variance / mean(y^2)")
    p.add_argument("--out", metavar="FILE", help="record file to write (.npz or .csv)")

    def _one_line_error(message, _p=p):
        print(f"gpnarx simulate: error: {message}", file=sys.stderr)
        sys.exit(2)

    p.error = _one_line_error
    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- argument parsing
def _number(args, name: str, *, positive: bool = False, nonnegative: bool = False) -> float | None:
    raw = getattr(args, name)
    if raw is None:
        return None
    flag = "--" + name.replace("_", "-")
    try:
        v = float(raw)
    except (TypeError, ValueError):
        raise UsageError(f"{flag} must be a number, got {raw!r}") from None
    if not math.isfinite(v):
        raise UsageError(f"{flag} must be finite, got {raw!r}")
    if positive and v <= 0:
        raise UsageError(f"{flag} must be > 0, got {raw}")
    if nonnegative and v < 0:
        raise UsageError(f"{flag} must be >= 0, got {raw}")
    return v


def _seed(args) -> int | None:
    raw = args.seed
    if raw is None:
        return None
    try:
        s = int(raw)
    except (TypeError, ValueError):
        raise UsageError(f"--seed must be a non-negative integer, got {raw!r}") from None
    if s < 0:
        raise UsageError(f"--seed must be a non-negative integer, got {raw}")
    return s


def _parse(args) -> dict:
    system = args.system
    if system is None:
        raise UsageError(f"give the system to simulate: {' or '.join(SYSTEMS)}")
    if system not in SYSTEMS:
        raise UsageError(f"unknown system {system!r}; choose {' or '.join(SYSTEMS)}")
    exc = args.excitation
    if exc not in EXCITATIONS:
        raise UsageError(f"--excitation must be one of {', '.join(EXCITATIONS)}, got {exc!r}")
    if args.amplitude is None:
        raise UsageError("--amplitude is required (peak for sweep/sine, RMS for multisine/noise; N or V)")
    if not args.out:
        raise UsageError("--out FILE is required (.npz or .csv)")
    amplitude = _number(args, "amplitude", positive=True)
    spec = {"system": system, "excitation": exc, "amplitude": amplitude, "out": args.out}
    uses = USES[exc] | {"seed"} | ({"torque", "scatter"} if system == "bert-standin" else set())
    for name in ("f0", "f1", "rate", "freq", "duration", "seed", "torque", "scatter"):
        if getattr(args, name) is not None and name not in uses:
            if name in ("torque", "scatter"):
                raise UsageError(f"--{name} applies only to bert-standin")
            raise UsageError(f"--{name} does not apply to --excitation {exc}")
    defaults = DEFAULTS[system][exc]
    for name in ("f0", "f1", "rate", "freq", "duration"):
        if name in defaults:
            v = _number(args, name, nonnegative=(name == "f0"), positive=(name != "f0"))
            spec[name] = defaults[name] if v is None else v
    spec["seed"] = _seed(args)
    spec["torque"] = None
    spec["scatter"] = None
    if system == "bert-standin":
        t = _number(args, "torque", positive=True)
        spec["torque"] = 5.0 if t is None else t
        k = _number(args, "scatter", nonnegative=True)
        if k is not None and k > 100:
            raise UsageError(f"--scatter must be between 0 and 100 (1 = calibrated default), got {k:g}")
        spec["scatter"] = 1.0 if k is None else k
    nf = _number(args, "noise_fraction", nonnegative=True)
    spec["noise_fraction"] = 0.0 if nf is None else nf
    return spec


# ----------------------------------------------------------------------------- excitation
# ----------------------------------------------------------------------------- simulation
class _Progress:
    """tqdm bar on stderr for long runs (disabled when short or stderr is not a TTY)."""

    def __init__(self, total: int, seconds: float, desc: str):
        self.bar = None
        if seconds > PROGRESS_ABOVE:
            try:
                from gpnarx._progress import progress_bar

                self.bar = progress_bar(total=total, desc=desc, unit="sample", file=sys.stderr, disable=None,
                                        leave=False)
            except ImportError:  # pragma: no cover
                self.bar = None

    def update(self, k: int) -> None:
        if self.bar is not None:
            self.bar.update(k)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _simulate_boucwen(u: np.ndarray, exc: str, spec: dict, fs: float) -> np.ndarray:
    # start-up: each simulator is imported when it runs (see gpnarx.cli)
    from gpnarx.training.simulators.boucwen import BoucWen

    bw = BoucWen(fs=fs)
    if exc == "multisine":
        n_per = bw.default_n_periods(u.size)
        prog = _Progress(n_per * u.size, n_per * u.size / fs, "bouc-wen")
        try:
            return bw.simulate(u, periodic=True, n_periods=n_per, callback=prog.update)["y"]
        finally:
            prog.close()
    if exc == "sine":
        pre, tail = sine_padding(fs, DEFAULTS["bouc-wen"]["preroll"])
        full = padded_sine(spec, fs, u.size, pre, tail)
        prog = _Progress(full.size, full.size / fs, "bouc-wen")
        try:
            return bw.simulate(full, callback=prog.update)["y"][pre : pre + u.size]
        finally:
            prog.close()
    prog = _Progress(u.size, u.size / fs, "bouc-wen")
    try:
        return bw.simulate(u, callback=prog.update)["y"]
    finally:
        prog.close()


def _simulate_standin(u: np.ndarray, exc: str, spec: dict, fs: float) -> np.ndarray:
    # start-up: each simulator is imported when it runs (see gpnarx.cli)
    from gpnarx.training.simulators.bert_standin import BertStandin

    sim = BertStandin(torque=spec["torque"], seed=spec["seed"], scatter=spec.get("scatter") or 1.0)
    if exc == "multisine":
        full, start = np.tile(u, 2), u.size
    elif exc == "sine":
        pre, tail = sine_padding(fs, DEFAULTS["bert-standin"]["preroll"])
        full, start = padded_sine(spec, fs, u.size, pre, tail), pre
    else:
        full, start = u, 0
    prog = _Progress(1, full.size / fs, "bert-standin")
    try:
        out = sim.simulate(full, fs=fs)
        prog.update(1)
    finally:
        prog.close()
    y = np.asarray(out["y"], dtype=np.float64).ravel()
    if y.size != full.size:
        raise CLIError(f"bert-standin returned {y.size} samples for an input of {full.size}")
    return y[start : start + u.size]


# ----------------------------------------------------------------------------- writing
def _atomic_target(path: str) -> str:
    path = os.path.abspath(os.path.expanduser(path))
    folder = os.path.dirname(path)
    if not os.path.isdir(folder):
        raise CLIError(f"--out: folder {folder} does not exist")
    return path


def _write_record(path: str, u: np.ndarray, y: np.ndarray, fs: float, units: dict) -> str:
    """Write ``u``, ``y`` (1-D float64) and ``fs`` [Hz] to ``path`` (.npz or .csv), atomically.

    The data go to a temporary file in the same folder which then replaces ``path`` (``os.replace``),
    so readers never see a half-written record. CSV: header line ``time,u,y`` then one row per
    sample (``time`` [s]; ``units`` are not stored in either format).
    """
    path = _atomic_target(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".npz", ".csv"):
        raise UsageError(f"--out: unsupported record extension {ext or '(none)'!r}; use .npz or .csv")
    u = np.ascontiguousarray(u, dtype=np.float64).ravel()
    y = np.ascontiguousarray(y, dtype=np.float64).ravel()
    with atomic_file(path) as fh:
        if ext == ".npz":
            np.savez(fh, u=u, y=y, fs=np.float64(fs))
        else:
            t = np.arange(u.size, dtype=np.float64) / fs
            np.savetxt(fh, np.column_stack([t, u, y]), delimiter=",", header="time,u,y", comments="", fmt="%.17g")
    return path


def _write(path: str, u: np.ndarray, y: np.ndarray, fs: float, units: dict, name: str, meta: dict) -> str:
    """Write with the shared writer ``storage.record_files.write_record`` (atomic, through :func:`_atomic_target`)."""
    target = _atomic_target(path)
    write_record(target, Record(u, y, fs, units=dict(units), name=name, meta=meta))
    return target


# ----------------------------------------------------------------------------- command
def run(args) -> dict:
    spec = _parse(args)
    system, exc = spec["system"], spec["excitation"]
    fs = DEFAULTS[system]["fs"]
    units = DEFAULTS[system]["units"]
    t0 = time.perf_counter()
    try:
        u, used = excitation(spec, fs)
    except ValueError as err:  # name the CLI flag, e.g. "f1 must ..." -> "--f1 must ..."
        msg = str(err)
        for name in ("f0", "f1", "rate", "freq", "duration", "amplitude"):
            if msg.startswith(name + " ") or msg.startswith(name + ":"):
                msg = "--" + msg
                break
        raise UsageError(msg) from None
    if system == "bouc-wen":
        y = _simulate_boucwen(u, exc, spec, fs)
    else:
        y = _simulate_standin(u, exc, spec, fs)
    if not np.all(np.isfinite(y)):
        raise CLIError(f"{system} simulation produced non-finite output; lower --amplitude")
    nf = spec["noise_fraction"]
    noise_std = 0.0
    if nf > 0:
        rng = np.random.default_rng(None if spec["seed"] is None else [spec["seed"], 0x6E6F697365])
        noise_std = math.sqrt(nf * float(np.mean(y * y)))
        y = y + rng.normal(0.0, noise_std, size=y.size)
    elapsed = time.perf_counter() - t0
    meta = {
        "system": system,
        "excitation": exc,
        "amplitude": spec["amplitude"],
        "amplitude_kind": "peak" if exc in ("sweep", "sine") else "rms",
        "seed": spec["seed"],
        "noise_fraction": nf,
        "noise_std": noise_std,
        **used,
    }
    if spec["torque"] is not None:
        meta["torque"] = spec["torque"]
    if spec.get("scatter") is not None:
        meta["scatter"] = spec["scatter"]
    name = f"{system} {exc} {spec['amplitude']:g} {units['u']}"
    path = _write(spec["out"], u, y, fs, units, name, meta)
    return {
        "path": path,
        **meta,
        "fs": fs,
        "n": int(u.size),
        "duration": u.size / fs,
        "units": dict(units),
        "u_rms": float(np.sqrt(np.mean(u * u))),
        "y_rms": float(np.sqrt(np.mean(y * y))),
        "y_peak": float(np.max(np.abs(y))),
        "elapsed_s": elapsed,
    }
