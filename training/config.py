"""Dataset configuration (TOML, read with ``tomllib``).

A dataset config names the records of a study and their roles, the system's sampling frequency and
units, the physical constants used for restoring-force loops, the model settings and the lag ranges.
The training pipeline, the lag-surface search and the novelty calibration read it. Schema (every
key name below is a contract)::

    name = "bouc-wen"                 # bundle name (required)
    description = "..."               # free text

    [system]
    fs = 750.0                        # Hz (required); every record must have this fs
    units = { u = "N", y = "m" }      # every record must match (records without units take these)
    output = "displacement"           # or "velocity": what y is

    [physics]                         # restoring force R = input_gain * u - mass * acceleration [N]
    mass = 2.0                        # kg (modal mass for the BERT stand-in)
    input_gain = 1.0                  # N per input unit (N/V for a shaker voltage); default 1.0

    [model]
    ny = 20                           # output lags (omit when chosen by the lag surface)
    nu = 17                           # input lags
    kernel = "matern32+cubic"         # "rbf", "matern32", "rbf+cubic", "matern32+cubic" (eq. 12)
    mode = "exact"                    # "exact" | "sparse"
    inducing = 256                    # inducing points (sparse mode)
    max_train_points = 2000           # training-point cap
    selection = "stride"              # "stride" | "random" | "resonance" (largest-|y| windows, sec 4.2)
    restarts = 3                      # ML-II restarts
    seed = 0
    noise_calibration = "none"        # "none" (ML-II's sigma_y^2, the paper) | "lags": raise sigma_y^2 to
                                      # its held-out ML value on the 'lags' records (model.calibration)
    band_calibration = "none"         # "none" | "lags": add the model-discrepancy term to the free-run
                                      # band, calibrated on the 'lags' records (model.discrepancy)
    band_window = 0.25                # [s] window of its local amplitude

    [lags]                            # lag-surface ranges, LO:HI inclusive, optional step LO:HI:STEP
    ny = "1:24"
    nu = "1:20"

    [predict]
    mc_paths = 1024                   # Monte Carlo paths
    confidence = 0.99

    [novelty]
    false_alarm_rate = 0.01
    method = "rms_standardised_residual"   # or "segment_median_rms" (robust to spikes, model.novelty)

    [[records]]                       # one table per record
    name = "sweep-10N"                # unique (required)
    roles = ["train"]                 # any of train, lags, verify, validate, healthy, damaged
    path = "data/sweep.npz"           # a record file or LMS folder (see training.records) ...
    simulate = { system = "bouc-wen", excitation = "sweep", amplitude = 10.0 }   # ... OR a simulation
    noise = { fraction = 0.1, reference = "sweep-10N", seed = 11 }
    window = [0.0, 2.0]               # optional time window [s], start inclusive, end exclusive
    fs = 1024.0                       # optional: fs of a file that stores none (CSV without time, NPY)
    meta = { torque = 5.0 }           # optional free metadata (copied into Record.meta)

Rules:

- ``path`` is relative to the config file's folder; ``${BERT_DATA}`` expands to the environment
  variable ``GPNARX_BERT_DATA`` or, if unset, ``<repo>/../shared/data/bert-t5nm`` (repo = the folder
  holding the ``training`` package); ``~`` expands to the home folder.
- ``simulate`` takes the arguments of ``gpnarx simulate``: ``system`` ("bouc-wen" or
  "bert-standin"), ``excitation`` ("sweep", "sine", "multisine", "noise"), ``amplitude`` (peak for
  sweep/sine, RMS for multisine/noise), and optionally ``f0``, ``f1``, ``rate``, ``freq``,
  ``duration``, ``seed``, ``torque`` and ``scatter`` (stand-in only), with the CLI's defaults and conventions
  (sines returned in steady state, multisines in periodic steady state, sweeps and noise from
  rest). ``y`` is the displacement or the velocity according to ``system.output``.
- ``noise`` adds Gaussian output noise of variance ``fraction * mean(y_ref^2)`` where ``y_ref`` is
  the *clean* (windowed) output of the record named by ``reference`` (default: the record itself),
  drawn from ``numpy.random.default_rng(seed)``. The noisy record keeps the clean output in
  ``Record.meta["clean_y"]`` (and the noise standard deviation in ``meta["noise_std"]``) so coverage
  can be scored against the noise-free output.
- Records are materialised lazily by :meth:`DatasetConfig.records_for` and cached.

Errors (missing ``name``/``system.fs``/``records``, no record with role ``train``, unknown roles or
options, bad values, fs or unit mismatches, unreadable records) raise :class:`ConfigError` (a
``ValueError``) with one line naming the file and the key.
"""
from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpnarx.model.novelty import METHODS as NOVELTY_METHODS
from gpnarx.model.records import Record, RecordError
from gpnarx.training import simulation_specs as specs
from gpnarx.training.records import RecordFileError, normalize_unit, read_record
from gpnarx.training.simulators.bert_standin import BertStandin
from gpnarx.training.simulators.boucwen import BoucWen

__all__ = [
    "ConfigError",
    "DatasetConfig",
    "RecordSpec",
    "ROLES",
    "KERNELS",
    "load_config",
    "parse_range",
    "bert_data_dir",
    "expand_path",
    "simulate_record",
]

ROLES = ("train", "lags", "verify", "validate", "healthy", "damaged")
KERNELS = ("rbf", "matern32", "rbf+cubic", "matern32+cubic")
MODES = ("exact", "sparse")
SELECTIONS = ("stride", "random", "resonance")
OUTPUTS = ("displacement", "velocity")
SIM_SYSTEMS = specs.SYSTEMS
SIM_EXCITATIONS = specs.EXCITATIONS
_SIM_KEYS = {"system", "excitation", "amplitude", "f0", "f1", "rate", "freq", "duration", "seed", "torque", "scatter"}
_RECORD_KEYS = {"name", "roles", "path", "simulate", "noise", "window", "meta", "fs"}
_NOISE_KEYS = {"fraction", "reference", "seed"}

MODEL_DEFAULTS = {
    "kernel": "matern32+cubic",
    "mode": "exact",
    "inducing": 256,
    "max_train_points": 2000,
    "selection": "stride",
    "restarts": 3,
    "seed": 0,
    "noise_calibration": "none",
    "band_calibration": "none",
    "band_window": 0.25,
}
NOISE_CALIBRATIONS = ("none", "lags")
BAND_CALIBRATIONS = ("none", "lags")
PREDICT_DEFAULTS = {"mc_paths": 1024, "confidence": 0.99}
NOVELTY_DEFAULTS = {"false_alarm_rate": 0.01, "method": "rms_standardised_residual"}  # model.novelty.METHODS
PHYSICS_DEFAULTS = {"mass": None, "input_gain": 1.0}


class ConfigError(ValueError):
    """A dataset config is invalid; the message is one line naming the file and the key."""


def _err(path, key: str, problem: str) -> ConfigError:
    where = f"{path}: " if path else ""
    k = f"{key}: " if key else ""
    return ConfigError(" ".join(f"{where}{k}{problem}".split()))


# ============================================================================ ranges and paths
def parse_range(spec) -> list[int]:
    """Lag range to a list of ints: ``"1:24"`` (inclusive), ``"1:24:2"``, ``"5"``, ``"1,3,5"``,
    an int, or a list of ints (returned validated, so the call is idempotent)."""
    if isinstance(spec, bool):
        raise ConfigError(f"range must be LO:HI[:STEP] or an integer, got {spec!r}")
    if isinstance(spec, (int, np.integer)):
        vals = [int(spec)]
    elif isinstance(spec, (list, tuple)):
        vals = []
        for v in spec:
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ConfigError(f"range list must hold integers, got {v!r}")
            vals.append(int(v))
        if not vals:
            raise ConfigError("range list is empty")
    elif isinstance(spec, str):
        s = spec.strip()
        try:
            if ":" in s:
                parts = [p.strip() for p in s.split(":")]
                if len(parts) not in (2, 3) or not all(parts):
                    raise ValueError
                lo, hi = int(parts[0]), int(parts[1])
                step = int(parts[2]) if len(parts) == 3 else 1
                if step < 1:
                    raise ConfigError(f"range {spec!r}: step must be >= 1")
                if lo > hi:
                    raise ConfigError(f"range {spec!r}: LO must not exceed HI")
                vals = list(range(lo, hi + 1, step))
            elif "," in s:
                vals = [int(p) for p in s.split(",")]
            else:
                vals = [int(s)]
        except ConfigError:
            raise
        except ValueError:
            raise ConfigError(f"range must be LO:HI[:STEP] (e.g. 1:24 or 1:24:2), got {spec!r}") from None
    else:
        raise ConfigError(f"range must be LO:HI[:STEP] or an integer, got {spec!r}")
    if any(v < 0 for v in vals):
        raise ConfigError(f"range {spec!r}: lags must be >= 0")
    return vals


def bert_data_dir() -> Path:
    """Folder of the real BERT records: ``$GPNARX_BERT_DATA``, else the first existing of
    ``<source checkout>/../shared/data/bert-t5nm`` and ``./shared/data/bert-t5nm`` or
    ``../shared/data/bert-t5nm`` from the working directory (the first candidate when none exists)."""
    env = os.environ.get("GPNARX_BERT_DATA")
    if env:
        return Path(env).expanduser()
    tail = Path("shared") / "data" / "bert-t5nm"
    candidates = [Path(__file__).resolve().parent.parent.parent / tail, Path.cwd() / tail, Path.cwd().parent / tail]
    return next((c for c in candidates if c.is_dir()), candidates[0])


def expand_path(raw: str, base: Path) -> Path:
    """Expand ``${BERT_DATA}`` and ``~`` and resolve relative to ``base`` (the config's folder)."""
    s = str(raw).replace("${BERT_DATA}", str(bert_data_dir())).replace("$BERT_DATA", str(bert_data_dir()))
    p = Path(s).expanduser()
    return p if p.is_absolute() else (base / p)


# ============================================================================ dataclasses
@dataclass
class RecordSpec:
    """One ``[[records]]`` entry (see the module docstring)."""

    name: str
    roles: list
    path: Path | None = None
    simulate: dict | None = None
    noise: dict | None = None
    window: tuple | None = None
    fs: float | None = None
    meta: dict = field(default_factory=dict)

    @property
    def source(self) -> str:
        if self.path is not None:
            return str(self.path)
        sim = self.simulate or {}
        return f"simulate {sim.get('system')} {sim.get('excitation')} {sim.get('amplitude')}"


@dataclass
class DatasetConfig:
    """A loaded dataset config. ``system``, ``physics``, ``model``, ``lags``, ``predict`` and
    ``novelty`` are plain dicts with defaults filled in; ``records`` the record specs in file order;
    ``path`` the config file."""

    name: str
    description: str
    system: dict
    physics: dict
    model: dict
    lags: dict
    predict: dict
    novelty: dict
    records: list
    path: Path
    extra: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _clean: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    # ------------------------------------------------------------------ access
    @property
    def fs(self) -> float:
        return float(self.system["fs"])

    @property
    def units(self) -> dict:
        return dict(self.system["units"])

    def spec(self, name: str) -> RecordSpec:
        for s in self.records:
            if s.name == name:
                return s
        raise _err(self.path, "records", f"no record named {name!r}")

    def names_for(self, role: str) -> list[str]:
        """Names of the records that have ``role``."""
        self._check_role(role)
        return [s.name for s in self.records if role in s.roles]

    def records_for(self, role: str) -> list[Record]:
        """The records with ``role``, materialised (simulated or read, windowed, noise added) on
        first use and cached."""
        self._check_role(role)
        return [self.record(s.name) for s in self.records if role in s.roles]

    def record(self, name: str) -> Record:
        """One record by name (materialised and cached)."""
        if name not in self._cache:
            spec = self.spec(name)
            rec = self._clean_record(spec)
            if spec.noise:
                rec = self._add_noise(spec, rec)
            self._cache[name] = rec
        return self._cache[name]

    def all_records(self) -> list[Record]:
        return [self.record(s.name) for s in self.records]

    def _check_role(self, role: str) -> None:
        if role not in ROLES:
            raise _err(self.path, "role", f"unknown role {role!r}; roles are {', '.join(ROLES)}")

    # ------------------------------------------------------------------ materialisation
    def _clean_record(self, spec: RecordSpec) -> Record:
        if spec.name in self._clean:
            return self._clean[spec.name]
        key = f"records.{spec.name}"
        if spec.simulate is not None:
            try:
                rec = simulate_record(spec.simulate, output=self.system["output"], name=spec.name)
            except ConfigError as exc:
                raise _err(self.path, f"{key}.simulate", str(exc)) from None
            except (ValueError, RecordError) as exc:
                raise _err(self.path, f"{key}.simulate", str(exc)) from None
        else:
            try:
                rec = read_record(spec.path, fs=spec.fs, name=spec.name, fs_default=self.fs)
            except RecordFileError as exc:
                raise _err(self.path, f"{key}.path", str(exc)) from None
        self._check_fs(spec, rec)
        rec = self._check_units(spec, rec)
        if spec.window is not None:
            try:
                rec = rec.window(*spec.window)
            except RecordError as exc:
                raise _err(self.path, f"{key}.window", str(exc).split(": ", 1)[-1]) from None
            rec.name = spec.name
        rec.meta.update(spec.meta)
        rec.meta["roles"] = list(spec.roles)
        rec.meta["config_record"] = spec.name
        if spec.window is not None:
            rec.meta["window"] = list(spec.window)
        self._clean[spec.name] = rec
        return rec

    def _check_fs(self, spec: RecordSpec, rec: Record) -> None:
        fs = self.fs
        if abs(rec.fs - fs) <= 1e-6 * fs:
            return
        other = next(
            (n for n, r in self._clean.items() if n != spec.name and abs(r.fs - fs) <= 1e-6 * fs), None
        )
        like = ""
        if other is not None:
            like = f", as record {other!r} ({self.spec(other).source}) has"
        raise _err(
            self.path, f"records.{spec.name}",
            f"record {spec.name!r} ({spec.source}) has fs {rec.fs:g} Hz but system.fs is {fs:g} Hz{like}",
        )

    def _check_units(self, spec: RecordSpec, rec: Record) -> Record:
        want = self.system["units"]
        units = dict(rec.units)
        for k in ("u", "y"):
            have = units.get(k, "") or ""
            if not have:
                units[k] = want.get(k, "")
            elif want.get(k) and have != want[k]:
                raise _err(
                    self.path, f"records.{spec.name}",
                    f"record {spec.name!r} ({spec.source}) has {k} in {have!r} but system.units.{k} is {want[k]!r}",
                )
        rec.units = units
        return rec

    def _add_noise(self, spec: RecordSpec, rec: Record) -> Record:
        nz = spec.noise
        ref_name = nz.get("reference", spec.name)
        ref = rec if ref_name == spec.name else self._clean_record(self.spec(ref_name))
        if ref.y is None:
            raise _err(self.path, f"records.{spec.name}.noise.reference", f"record {ref_name!r} has no output y")
        if rec.y is None:
            raise _err(self.path, f"records.{spec.name}.noise", "the record has no output y to add noise to")
        var = float(nz["fraction"]) * float(np.mean(ref.y * ref.y))
        std = math.sqrt(var)
        rng = np.random.default_rng(nz.get("seed"))
        noisy = rec.y + rng.normal(0.0, std, size=rec.y.size)
        meta = dict(rec.meta)
        meta.update(clean_y=rec.y.copy(), noise_std=std, noise_fraction=float(nz["fraction"]),
                    noise_reference=ref_name)
        return Record(rec.u.copy(), noisy, rec.fs, dict(rec.units), rec.name, meta)


# ============================================================================ simulation specs
def simulate_record(sim: dict, output: str = "default", name: str | None = None) -> Record:
    """Simulate a record from a ``simulate`` table (the arguments of ``gpnarx simulate``).

    output: "displacement", "velocity" or "default" (the system's own: Bouc-Wen displacement,
    stand-in velocity). Uses the CLI's defaults (``gpnarx.training.simulation_specs.DEFAULTS``) and conventions.
    """
    unknown = set(sim) - _SIM_KEYS
    if unknown:
        raise ConfigError(f"unknown option(s) {', '.join(sorted(unknown))}; allowed: {', '.join(sorted(_SIM_KEYS))}")
    system = sim.get("system")
    if system not in SIM_SYSTEMS:
        raise ConfigError(f"system must be one of {', '.join(SIM_SYSTEMS)}, got {system!r}")
    exc = sim.get("excitation", "sweep")
    if exc not in SIM_EXCITATIONS:
        raise ConfigError(f"excitation must be one of {', '.join(SIM_EXCITATIONS)}, got {exc!r}")
    if "amplitude" not in sim:
        raise ConfigError("amplitude is required (peak for sweep/sine, RMS for multisine/noise)")
    for key in ("torque", "scatter"):
        if key in sim and system != "bert-standin":
            raise ConfigError(f"{key} applies only to bert-standin")
    defaults = specs.DEFAULTS[system]
    uses = specs.USES[exc]
    for k in ("f0", "f1", "rate", "freq", "duration"):
        if k in sim and k not in uses:
            raise ConfigError(f"{k} does not apply to excitation {exc}")
    spec = {"system": system, "excitation": exc, "amplitude": _num(sim["amplitude"], "amplitude", positive=True)}
    for k in ("f0", "f1", "rate", "freq", "duration"):
        if k in defaults[exc]:
            spec[k] = _num(sim[k], k, positive=(k != "f0")) if k in sim else defaults[exc][k]
    seed = sim.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    spec["seed"] = seed
    spec["torque"] = _num(sim.get("torque", 5.0), "torque", positive=True) if system == "bert-standin" else None
    spec["scatter"] = None
    if system == "bert-standin":
        spec["scatter"] = _num(sim.get("scatter", 1.0), "scatter")
        if not 0.0 <= spec["scatter"] <= 100.0:
            raise ConfigError(f"scatter must be between 0 and 100 (1 = calibrated default), got {spec['scatter']:g}")
    fs = float(defaults["fs"])
    u, used = specs.excitation(spec, fs)
    if output == "default":
        output = "displacement" if system == "bouc-wen" else "velocity"
    if output not in OUTPUTS:
        raise ConfigError(f"output must be one of {', '.join(OUTPUTS)}, got {output!r}")
    if system == "bouc-wen":
        bw = BoucWen(fs=fs)
        key = "y" if output == "displacement" else "v"
        if exc == "multisine":
            y = bw.simulate(u, periodic=True)[key]
        elif exc == "sine":
            pre, tail = specs.sine_padding(fs, defaults["preroll"])
            y = bw.simulate(specs.padded_sine(spec, fs, u.size, pre, tail))[key][pre : pre + u.size]
        else:
            y = bw.simulate(u)[key]
        units = {"u": "N", "y": "m" if output == "displacement" else "m/s"}
    else:
        model = BertStandin(torque=spec["torque"], seed=seed, scatter=spec["scatter"])
        key = "x" if output == "displacement" else "y"
        if exc == "multisine":
            full, start = np.tile(u, 2), u.size
        elif exc == "sine":
            pre, tail = specs.sine_padding(fs, defaults["preroll"])
            full, start = specs.padded_sine(spec, fs, u.size, pre, tail), pre
        else:
            full, start = u, 0
        y = model.simulate(full, fs=fs)[key][start : start + u.size]
        units = {"u": "V", "y": "m" if output == "displacement" else "m/s"}
    meta = {"system": system, "excitation": exc, "amplitude": spec["amplitude"],
            "amplitude_kind": "peak" if exc in ("sweep", "sine") else "rms", "seed": seed, **used}
    if spec["torque"] is not None:
        meta["torque"] = spec["torque"]
        meta["scatter"] = spec["scatter"]
    return Record(u, np.asarray(y, dtype=np.float64), fs, units, name or f"{system}-{exc}", meta)


def _num(v, key: str, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{key} must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v) or (positive and v <= 0) or v < 0:
        raise ConfigError(f"{key} must be {'> 0' if positive else '>= 0'}, got {v}")
    return v


# ============================================================================ loading
def load_config(path) -> DatasetConfig:
    """Read and validate a dataset config (see the module docstring). Records are not read yet."""
    p = Path(os.fspath(path)).expanduser()
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise _err(p, "", "config file not found") from None
    except OSError as exc:
        raise _err(p, "", f"cannot read the config ({exc.strerror or exc})") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise _err(p, "", "config is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise _err(p, "", f"invalid TOML ({exc})") from None
    return _build(doc, p.resolve())


def _table(doc: dict, key: str, path) -> dict:
    v = doc.get(key, {})
    if not isinstance(v, dict):
        raise _err(path, key, f"must be a table, got {type(v).__name__}")
    return dict(v)


def _pos_int(v, key, path, minimum=1) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise _err(path, key, f"must be an integer >= {minimum}, got {v!r}")
    return int(v)


def _pos_float(v, key, path, allow_none=False) -> float | None:
    if v is None and allow_none:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise _err(path, key, f"must be a positive number, got {v!r}")
    return float(v)


def _choice(v, key, path, choices) -> str:
    if v not in choices:
        raise _err(path, key, f"must be one of {', '.join(repr(c) for c in choices)}, got {v!r}")
    return v


def _build(doc: dict, path: Path) -> DatasetConfig:
    name = doc.get("name")
    if name is None:
        raise _err(path, "name", "missing required key")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise _err(path, "name", f"must be a name of letters, digits, '.', '_' or '-', got {name!r}")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise _err(path, "description", "must be a string")

    system = _table(doc, "system", path)
    if "fs" not in system:
        raise _err(path, "system.fs", "missing required key (sampling frequency in Hz)")
    system["fs"] = _pos_float(system["fs"], "system.fs", path)
    units = system.get("units", {"u": "", "y": ""})
    if not isinstance(units, dict):
        raise _err(path, "system.units", "must be a table like { u = \"N\", y = \"m\" }")
    bad = set(units) - {"u", "y"}
    if bad:
        raise _err(path, "system.units", f"unknown key(s) {', '.join(sorted(bad))}; use u and y")
    try:
        system["units"] = {k: normalize_unit(units.get(k, ""), path) for k in ("u", "y")}
    except RecordFileError as exc:
        raise _err(path, "system.units", exc.problem) from None
    system["output"] = _choice(system.get("output", "displacement"), "system.output", path, OUTPUTS)

    physics = {**PHYSICS_DEFAULTS, **_table(doc, "physics", path)}
    physics["mass"] = _pos_float(physics["mass"], "physics.mass", path, allow_none=True)
    physics["input_gain"] = _pos_float(physics["input_gain"], "physics.input_gain", path)

    model = {**MODEL_DEFAULTS, **_table(doc, "model", path)}
    for k in ("ny", "nu"):
        if k in model:
            model[k] = _pos_int(model[k], f"model.{k}", path)
    model["kernel"] = _choice(model["kernel"], "model.kernel", path, KERNELS)
    model["mode"] = _choice(model["mode"], "model.mode", path, MODES)
    model["selection"] = _choice(model["selection"], "model.selection", path, SELECTIONS)
    model["inducing"] = _pos_int(model["inducing"], "model.inducing", path)
    model["max_train_points"] = _pos_int(model["max_train_points"], "model.max_train_points", path)
    model["restarts"] = _pos_int(model["restarts"], "model.restarts", path, minimum=0)
    model["seed"] = _pos_int(model["seed"], "model.seed", path, minimum=0)
    model["noise_calibration"] = _choice(model["noise_calibration"], "model.noise_calibration", path,
                                         NOISE_CALIBRATIONS)
    model["band_calibration"] = _choice(model["band_calibration"], "model.band_calibration", path,
                                        BAND_CALIBRATIONS)
    bw = model["band_window"]
    if isinstance(bw, bool) or not isinstance(bw, (int, float)) or not 0 < bw <= 10:
        raise _err(path, "model.band_window", f"must be a number of seconds in (0, 10], got {bw!r}")
    model["band_window"] = float(bw)

    lags = _table(doc, "lags", path)
    for k, v in lags.items():
        try:
            parse_range(v)
        except ConfigError as exc:
            raise _err(path, f"lags.{k}", str(exc)) from None

    predict = {**PREDICT_DEFAULTS, **_table(doc, "predict", path)}
    predict["mc_paths"] = _pos_int(predict["mc_paths"], "predict.mc_paths", path)
    conf = predict["confidence"]
    if isinstance(conf, bool) or not isinstance(conf, (int, float)) or not 0 < conf < 1:
        raise _err(path, "predict.confidence", f"must be between 0 and 1, got {conf!r}")
    predict["confidence"] = float(conf)
    predict.setdefault("method", "mc")
    if predict["method"] not in ("mc", "linear"):
        raise _err(path, "predict.method", f"must be 'mc' or 'linear', got {predict['method']!r}")

    novelty = {**NOVELTY_DEFAULTS, **_table(doc, "novelty", path)}
    far = novelty["false_alarm_rate"]
    if isinstance(far, bool) or not isinstance(far, (int, float)) or not 0 < far < 1:
        raise _err(path, "novelty.false_alarm_rate", f"must be between 0 and 1, got {far!r}")
    novelty["false_alarm_rate"] = float(far)
    if novelty["method"] not in NOVELTY_METHODS:
        raise _err(path, "novelty.method",
                   f"must be one of {', '.join(NOVELTY_METHODS)}, got {novelty['method']!r}")

    raw_records = doc.get("records")
    if raw_records is None:
        raise _err(path, "records", "missing required key (at least one [[records]] table with role 'train')")
    if not isinstance(raw_records, list) or not all(isinstance(r, dict) for r in raw_records):
        raise _err(path, "records", "must be an array of tables ([[records]])")
    specs = [_record_spec(r, i, path) for i, r in enumerate(raw_records)]
    seen = set()
    for s in specs:
        if s.name in seen:
            raise _err(path, f"records.{s.name}", "duplicate record name")
        seen.add(s.name)
    for s in specs:
        if s.noise and s.noise.get("reference", s.name) not in seen:
            raise _err(path, f"records.{s.name}.noise.reference", f"no record named {s.noise['reference']!r}")
    if not any("train" in s.roles for s in specs):
        raise _err(path, "records", "no record has role 'train'")
    for key in ("noise_calibration", "band_calibration"):
        if model[key] != "lags":
            continue
        held = [s for s in specs if "lags" in s.roles]
        if not held:
            raise _err(path, f"model.{key}", "'lags' needs at least one record with role 'lags' "
                       "(held out from training)")
        for s in held:
            if "train" in s.roles:
                raise _err(path, f"records.{s.name}.roles", f"a 'lags' record calibrates the band "
                           f"(model.{key} = 'lags') and must not also have role 'train'")

    known = {"name", "description", "system", "physics", "model", "lags", "predict", "novelty", "records"}
    extra = {k: v for k, v in doc.items() if k not in known}
    return DatasetConfig(name, description, system, physics, model, lags, predict, novelty, specs, path, extra)


def _record_spec(r: dict, i: int, path: Path) -> RecordSpec:
    name = r.get("name")
    key = f"records[{i}]"
    if not isinstance(name, str) or not name.strip():
        raise _err(path, f"{key}.name", "missing required key (a unique record name)")
    key = f"records.{name}"
    unknown = set(r) - _RECORD_KEYS
    if unknown:
        raise _err(path, key,
                   f"unknown key(s) {', '.join(sorted(unknown))}; allowed: {', '.join(sorted(_RECORD_KEYS))}")
    roles = r.get("roles")
    if roles is None:
        raise _err(path, f"{key}.roles", "missing required key (e.g. roles = [\"train\"])")
    if isinstance(roles, str):
        roles = [roles]
    if not isinstance(roles, list) or not roles or not all(isinstance(x, str) for x in roles):
        raise _err(path, f"{key}.roles", "must be a non-empty list of role names")
    for role in roles:
        if role not in ROLES:
            raise _err(path, f"{key}.roles", f"unknown role {role!r}; roles are {', '.join(ROLES)}")
    has_path, has_sim = "path" in r, "simulate" in r
    if has_path == has_sim:
        raise _err(path, key, "give exactly one of path or simulate")
    rpath = sim = None
    if has_path:
        if not isinstance(r["path"], str) or not r["path"].strip():
            raise _err(path, f"{key}.path", "must be a file or folder path string")
        rpath = expand_path(r["path"], path.parent)
    else:
        sim = r["simulate"]
        if not isinstance(sim, dict):
            raise _err(path, f"{key}.simulate", "must be a table like { system = \"bouc-wen\", ... }")
        bad = set(sim) - _SIM_KEYS
        if bad:
            raise _err(path, f"{key}.simulate",
                       f"unknown option(s) {', '.join(sorted(bad))}; allowed: {', '.join(sorted(_SIM_KEYS))}")
        if sim.get("system") not in SIM_SYSTEMS:
            raise _err(path, f"{key}.simulate.system",
                       f"must be one of {', '.join(SIM_SYSTEMS)}, got {sim.get('system')!r}")
        if sim.get("excitation", "sweep") not in SIM_EXCITATIONS:
            raise _err(path, f"{key}.simulate.excitation",
                       f"must be one of {', '.join(SIM_EXCITATIONS)}, got {sim.get('excitation')!r}")
        if "amplitude" not in sim:
            raise _err(path, f"{key}.simulate.amplitude", "missing required key")
        sim = dict(sim)
    noise = r.get("noise")
    if noise is not None:
        if not isinstance(noise, dict):
            raise _err(path, f"{key}.noise", "must be a table like { fraction = 0.1, reference = \"...\", seed = 1 }")
        bad = set(noise) - _NOISE_KEYS
        if bad:
            raise _err(path, f"{key}.noise",
                       f"unknown key(s) {', '.join(sorted(bad))}; allowed: fraction, reference, seed")
        if "fraction" not in noise:
            raise _err(path, f"{key}.noise.fraction", "missing required key")
        fr = noise["fraction"]
        if isinstance(fr, bool) or not isinstance(fr, (int, float)) or not math.isfinite(fr) or fr < 0:
            raise _err(path, f"{key}.noise.fraction", f"must be a number >= 0, got {fr!r}")
        sd = noise.get("seed")
        if sd is not None and (isinstance(sd, bool) or not isinstance(sd, int) or sd < 0):
            raise _err(path, f"{key}.noise.seed", f"must be a non-negative integer, got {sd!r}")
        if "reference" in noise and not isinstance(noise["reference"], str):
            raise _err(path, f"{key}.noise.reference", "must be a record name")
        noise = dict(noise)
    window = r.get("window")
    if window is not None:
        if (not isinstance(window, list) or len(window) != 2
                or not all(isinstance(w, (int, float)) and not isinstance(w, bool) for w in window)
                or not 0 <= window[0] < window[1]):
            raise _err(path, f"{key}.window", f"must be [t0, t1] in s with 0 <= t0 < t1, got {window!r}")
        window = (float(window[0]), float(window[1]))
    fs = r.get("fs")
    if fs is not None:
        fs = _pos_float(fs, f"{key}.fs", path)
    meta = r.get("meta", {})
    if not isinstance(meta, dict):
        raise _err(path, f"{key}.meta", "must be a table")
    return RecordSpec(name, list(roles), rpath, sim, noise, window, fs, dict(meta))
