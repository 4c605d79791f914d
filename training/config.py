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
    inputs = ["Shaker:-X"]            # optional: the input channels by name, in order (several: a model with
    outputs = ["Laser:+X", "Acc1:+X"] # several inputs or outputs, ``model.mimo``); each record is read with
                                      # these channels (``read_record(inputs=, outputs=)``: an LMS folder's
                                      # channel labels, an .npz's channels_u / channels_y); absent: the
                                      # record's own u and y (an LMS folder's shaker and laser), as before

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
                                      # its held-out ML value on the 'lags' records (model.heldout_noise)
    band_calibration = "none"         # "none" | "lags": add the model-discrepancy term to the free-run
                                      # band, calibrated on the 'lags' records (model.discrepancy)
    band_window = 0.25                # [s] window of its local amplitude
    band_window_kind = "centred"      # "centred" | "trailing": the window ends at each sample (causal: a
                                      # stream's chunks get the whole record's band, docs/api.md)
    band_hold = 0.0                   # [s] time constant of the held amplitude (0: none): after a large
                                      # response the band keeps a decaying share of its size
    band_gp_scale = "fixed"           # "fixed" | "calibrated": multiply the propagated band by a factor
                                      # calibrated with the scale on the 'lags' records (model.discrepancy)
    lengthscale_refine = "none"       # "none" (ML-II's, the paper) | "lags": the lengthscales moved by one
                                      # factor, kept by free-run fit on the 'lags' records (training.hyper_refine)
    lengthscale_refine_tolerance = 1.0  # [points of fit] a 'lags' record may lose against ML-II's lengthscales
    hyper = "subset"                  # sparse mode: "subset" (exact ML-II on the capped rows) | "vfe"
    fit_backend = "numpy"             # "numpy" | "jax": ML-II and the exact posterior's solves on the JAX
                                      # device (a GPU: exact mode at 10-20 thousand rows; docs/accelerator.md)

    [lags]                            # lag-surface ranges, LO:HI inclusive, optional step LO:HI:STEP
    ny = "1:24"
    nu = "1:20"

    [predict]
    mc_paths = 1024                   # Monte Carlo paths
    confidence = 0.99
    method = "mc"                     # or "linear": the report's free runs and the bundle's default

    [novelty]
    false_alarm_rate = 0.01
    method = "rms_standardised_residual"   # or "segment_median_rms" (robust to spikes, model.novelty)

    [[records]]                       # one table per record
    name = "sweep-10N"                # unique (required)
    roles = ["train"]                 # any of train, lags, verify, validate, healthy, damaged
    path = "data/sweep.npz"           # a record file or LMS folder (see storage.record_files) ...
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

The schema is declared once, as the pydantic models of :mod:`gpnarx.training.config_schema` (its
docstring lists every table with its limits). ``load_config`` validates the TOML document with them
and builds :class:`DatasetConfig`'s plain dicts from the validated tables. Unknown keys are refused
in ``[[records]]``, ``simulate``, ``noise`` and ``system.units`` and kept elsewhere (top-level ones
in ``DatasetConfig.extra``).

Errors (missing ``name``/``system.fs``/``records``, no record with role ``train``, unknown roles, keys
or options (every table refuses keys it does not know), bad values, fs or unit mismatches, unreadable
records) raise :class:`ConfigError` (a ``ValueError``) with one line naming the file and the dotted
key, e.g.
``cfg.toml: model.inducing: must be an integer >= 1, got 0`` or
``cfg.toml: records.sweep-10N.noise.fraction: must be a number >= 0, got -1`` (a record without a
valid name is ``records[i]``).
"""
from __future__ import annotations

import math
import os
import tomllib
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from gpnarx.model.record import Record, RecordError, allowing_gaps
from gpnarx.storage.record_files import RecordFileError, read_record
from gpnarx.training import config_schema as schema
from gpnarx.training import simulation_specs as specs
from gpnarx.training.config_schema import ConfigError, parse_range
from gpnarx.training.datapaths import bert_data_dir
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

# the schema's choices, and its tables' defaults
ROLES, KERNELS, MODES, SELECTIONS = schema.ROLES, schema.KERNELS, schema.MODES, schema.SELECTIONS
OUTPUTS = schema.OUTPUTS
NOISE_CALIBRATIONS, BAND_CALIBRATIONS = schema.NOISE_CALIBRATIONS, schema.BAND_CALIBRATIONS
NOVELTY_METHODS, SIM_SYSTEMS, SIM_EXCITATIONS = schema.NOVELTY_METHODS, schema.SIM_SYSTEMS, schema.SIM_EXCITATIONS
MODEL_DEFAULTS = schema.ModelTable.defaults()
PREDICT_DEFAULTS = schema.PredictTable.defaults()
NOVELTY_DEFAULTS = schema.NoveltyTable.defaults()
PHYSICS_DEFAULTS = schema.PhysicsTable.defaults()


def _err(path, key: str, problem: str) -> ConfigError:
    where = f"{path}: " if path else ""
    k = f"{key}: " if key else ""
    return ConfigError(" ".join(f"{where}{k}{problem}".split()))


# ============================================================================ paths
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
        """One record by name (materialised and cached). A record file whose only role is ``train`` and that adds
        no noise may hold gaps (NaN samples, ``model.gaps``): no lag window of the fit crosses them; every other
        record must be gap-free (what the report scores is predicted whole)."""
        if name not in self._cache:
            spec = self.spec(name)
            gaps = set(spec.roles) <= {"train"} and spec.simulate is None and not spec.noise
            with allowing_gaps() if gaps else nullcontext():
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
                rec = read_record(spec.path, fs=spec.fs, name=spec.name, fs_default=self.fs,
                                  inputs=self.system.get("inputs"), outputs=self.system.get("outputs"))
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

    @property
    def channels(self) -> bool:
        """Whether the config selects its records' channels by name (``[system] inputs`` / ``outputs``)."""
        return bool(self.system.get("inputs") or self.system.get("outputs"))

    @property
    def several_channels(self) -> bool:
        """Whether the config's model has several inputs or outputs (``model.mimo``)."""
        return len(self.system.get("inputs") or [0]) > 1 or len(self.system.get("outputs") or [0]) > 1

    def _check_channel_units(self, spec: RecordSpec, rec: Record) -> Record:
        """A record read by channel names: every record's channels hold the units of the first one read, and a
        unit of ``system.units`` that the selected channels share must be theirs."""
        if simulated := spec.simulate is not None:
            try:
                rec = rec.select(self.system.get("inputs"), self.system.get("outputs"))
            except RecordError as exc:
                raise _err(self.path, f"records.{spec.name}", str(exc).split(": ", 1)[-1]) from None
        got = {"u": [(c.name, c.unit) for c in rec.input_channels()],
               "y": [(c.name, c.unit) for c in rec.output_channels()]}
        first = next((r for n, r in self._clean.items() if n != spec.name), None)
        for k, side in (("u", "inputs"), ("y", "outputs")):
            want = self.system["units"].get(k)
            common = {u for _, u in got[k]}
            if want and len(common) == 1 and common != {""} and common != {want}:
                raise _err(self.path, f"records.{spec.name}", f"record {spec.name!r} ({spec.source}) has {k} in "
                                                              f"{common.pop()!r} but system.units.{k} is {want!r}")
            if first is not None:
                ref = [(c.name, c.unit) for c in (first.input_channels() if k == "u" else first.output_channels())]
                if [u for _, u in got[k]] != [u for _, u in ref] and not simulated:
                    raise _err(self.path, f"records.{spec.name}",
                               f"record {spec.name!r} ({spec.source}) has {side} {got[k]} but record {first.name!r} "
                               f"has {ref}: every record's channels must hold the same units")
        return rec

    def _check_units(self, spec: RecordSpec, rec: Record) -> Record:
        if self.channels:
            return self._check_channel_units(spec, rec)
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
        rng = np.random.default_rng(nz.get("seed"))
        if rec.y.ndim == 2:  # several outputs: each channel's noise from its own reference level
            std = np.sqrt(float(nz["fraction"]) * np.mean(ref.y * ref.y, axis=0))
            noisy = rec.y + rng.normal(0.0, 1.0, size=rec.y.shape) * std
            std = [float(v) for v in std]
        else:
            var = float(nz["fraction"]) * float(np.mean(ref.y * ref.y))
            std = math.sqrt(var)
            noisy = rec.y + rng.normal(0.0, std, size=rec.y.size)
        meta = dict(rec.meta)
        meta.update(clean_y=rec.y.copy(), noise_std=std, noise_fraction=float(nz["fraction"]),
                    noise_reference=ref_name)
        return Record(rec.u.copy(), noisy, rec.fs, dict(rec.units), rec.name, meta, rec.channels)


# ============================================================================ simulation specs
def simulate_record(sim: dict, output: str = "default", name: str | None = None) -> Record:
    """Simulate a record from a ``simulate`` table (the arguments of ``gpnarx simulate``), checked
    with :class:`gpnarx.training.config_schema.Simulation` (a problem raises :class:`ConfigError`).

    output: "displacement", "velocity" or "default" (the system's own: Bouc-Wen displacement,
    stand-in velocity). Uses the CLI's defaults (``gpnarx.training.simulation_specs.DEFAULTS``) and conventions.
    """
    try:
        sim_ok = schema.Simulation.model_validate(sim)
    except ValidationError as exc:
        key, problem = schema.explain(exc, sim, schema.Simulation, missing="is required")
        raise ConfigError(f"{key} {problem}" if key else problem) from None
    system, exc, seed = sim_ok.system, sim_ok.excitation, sim_ok.seed
    defaults = specs.DEFAULTS[system]
    spec = {"system": system, "excitation": exc, "amplitude": sim_ok.amplitude}
    for k in schema.SIM_OPTIONS:
        if k in defaults[exc]:
            v = getattr(sim_ok, k)
            spec[k] = defaults[exc][k] if v is None else v
    spec["seed"] = seed
    spec["torque"] = spec["scatter"] = None
    if system == "bert-standin":
        spec["torque"] = 5.0 if sim_ok.torque is None else sim_ok.torque
        spec["scatter"] = 1.0 if sim_ok.scatter is None else sim_ok.scatter
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


def _build(doc: dict, path: Path) -> DatasetConfig:
    """Validate ``doc`` with the schema (``config_schema.DatasetDoc``) and build the config's plain dicts."""
    try:
        d = schema.DatasetDoc.model_validate(doc)
    except ValidationError as exc:
        key, problem = schema.explain(exc, doc)
        raise _err(path, key, problem) from None
    records = [_record_spec(r, raw, path) for r, raw in zip(d.records, doc["records"])]
    return DatasetConfig(d.name, d.description, d.system.as_dict(), d.physics.as_dict(), d.model.as_dict(),
                         dict(d.lags), d.predict.as_dict(), d.novelty.as_dict(), records, path,
                         dict(d.model_extra or {}))


def _record_spec(r: schema.RecordTable, raw: dict, path: Path) -> RecordSpec:
    """A validated record table as a :class:`RecordSpec`; ``simulate``, ``noise`` and ``meta`` stay as written."""
    return RecordSpec(
        r.name, list(r.roles),
        path=None if r.path is None else expand_path(r.path, path.parent),
        simulate=None if r.simulate is None else dict(raw["simulate"]),
        noise=None if r.noise is None else dict(raw["noise"]),
        window=r.window, fs=r.fs, meta=dict(r.meta),
    )
