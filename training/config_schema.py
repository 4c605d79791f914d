"""The dataset config's schema, declared once as pydantic models (the keys are described, with an
example, in :mod:`gpnarx.training.config`, which loads a config with these models).

One model per TOML table::

    DatasetDoc                the document: name (letters, digits, '.', '_', '-'; required),
                              description, [system], [physics], [model], [lags], [predict], [novelty],
                              [[records]] (required); other top-level keys are kept (DatasetConfig.extra)
      SystemTable             fs [Hz] > 0 (required), units (UnitsTable: u, y only), output, inputs and
                              outputs (channel names, unique, at most 64 each; absent: as before)
      PhysicsTable            mass [kg] > 0 (optional), input_gain [N per input unit] > 0
      ModelTable              ny, nu >= 1 (optional), kernel, mode, inducing >= 1, max_train_points >= 1,
                              selection, restarts >= 0, seed >= 0, noise_calibration, band_calibration,
                              band_window [s] in (0, 10], band_window_kind "centred" | "trailing",
                              band_hold [s] in [0, 60], band_gp_scale "fixed" | "calibrated",
                              lengthscale_refine "none" | "lags", lengthscale_refine_tolerance [points] in
                              [0, 100]
      lags                    any key: a lag range LO:HI[:STEP] (parse_range)
      PredictTable            mc_paths >= 1, confidence in (0, 1), method "mc" | "linear"
      NoveltyTable            false_alarm_rate in (0, 1), method (gpnarx.model.novelty.METHODS)
      RecordTable             name (unique, required), roles (of ROLES, required), path | simulate
                              (exactly one), noise, window [s] 0 <= t0 < t1, fs [Hz] > 0, meta
        SimulateTable         system, excitation, amplitude (required) and the other options' names
          Simulation          its values: amplitude > 0 [N or V], f0 >= 0 [Hz], f1, freq [Hz], rate
                              [Hz/s], duration [s], torque [N m] > 0, scatter in [0, 100], seed >= 0
        NoiseTable            fraction >= 0 (required), reference (an existing record), seed >= 0

Numbers are strict (a boolean or a string is not a number; an integer is where a float is asked
for), limits are ``Field`` constraints, choices are ``Literal``; the rules across keys (exactly
one of ``path``/``simulate``, unique record names, ``noise.reference`` naming a record, a record
with role 'train', the 'lags' records of ``noise_calibration``/``band_calibration``) are model
validators. Every table refuses unknown keys (a misspelt option is an error, not a silent default);
only the document keeps other top-level keys (``DatasetConfig.extra``).

A ``simulate`` table's values are checked when the record is simulated (:class:`Simulation`, used
by ``simulate_record``), as a file record's contents are when it is read: loading a config checks
the option names, the system, the excitation and that an amplitude is given.

:func:`explain` turns a ``ValidationError`` into one ``(dotted key, problem)`` pair, the key
naming the field as the config's author wrote it (``system.fs``, ``records.NAME.noise.fraction``,
``records[2].name`` when the record has no valid name) and the problem naming the limit
("must be an integer >= 1, got 0"). ``ConfigError`` and ``parse_range`` live here because the
schema's lag ranges use them; import them from :mod:`gpnarx.training.config`.
"""
from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal, get_args

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    WrapValidator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from gpnarx.checks import is_int
from gpnarx.model.discrepancy import WINDOW_KINDS as BAND_WINDOW_KINDS
from gpnarx.model.novelty import METHODS as NOVELTY_METHODS
from gpnarx.model.record import MAX_CHANNELS, RecordError
from gpnarx.storage.record_files import normalize_unit
from gpnarx.training import simulation_specs as specs
from gpnarx.training.hyper_refine import RULES as REFINE_RULES

ROLES = ("train", "lags", "verify", "validate", "healthy", "damaged")
KERNELS = ("rbf", "matern32", "rbf+cubic", "matern32+cubic")
MODES = ("exact", "sparse")
SELECTIONS = ("stride", "random", "resonance")
OUTPUTS = ("displacement", "velocity")
NOISE_CALIBRATIONS = ("none", "lags")
BAND_CALIBRATIONS = ("none", "lags")
BAND_GP_SCALES = ("fixed", "calibrated")
LENGTHSCALE_REFINES = REFINE_RULES
PREDICT_METHODS = ("mc", "linear")
SIM_SYSTEMS = specs.SYSTEMS
SIM_EXCITATIONS = specs.EXCITATIONS
SIM_OPTIONS = ("f0", "f1", "rate", "freq", "duration")  # the excitation options (specs.USES)
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]*$"


class ConfigError(ValueError):
    """A dataset config is invalid; the message is one line naming the file and the key."""


# ============================================================================ lag ranges
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
            if not is_int(v):
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


# ============================================================================ value types
def _problem(text: str, key: str = "") -> PydanticCustomError:
    """A validation error whose message is ``text`` as it is; ``key``: the dotted key it names,
    relative to where it is raised (a rule across keys raised by a table's model validator)."""
    return PydanticCustomError("config", "{problem}", {"problem": text, "key": key})


def _expect(expect: str) -> WrapValidator:
    """Any failure of the value (its type or a limit) reads "must be {expect}, got {value!r}"."""

    def check(value, handler):
        try:
            return handler(value)
        except ValidationError:
            raise _problem(f"must be {expect}, got {value!r}") from None

    return WrapValidator(check)


def _one_of(choices, quoted: bool = True) -> str:
    return "one of " + ", ".join(repr(c) if quoted else str(c) for c in choices)


def _choice(choices, expect: str | None = None):
    return Annotated[Literal[choices], _expect(expect or _one_of(choices))]


def _integer(ge: int, expect: str | None = None):
    return Annotated[int, Field(strict=True, ge=ge), _expect(expect or f"an integer >= {ge}")]


def _number(expect: str, **limits):
    """A float (an integer is one, a boolean or a string is not) within ``limits`` (gt, ge, lt, le;
    finite unless ``allow_inf_nan``)."""
    limits.setdefault("allow_inf_nan", False)
    return Annotated[float, Field(strict=True, **limits), _expect(expect)]


Count = _integer(1)  # an integer >= 1
Index = _integer(0)  # an integer >= 0 (restarts, model.seed)
Seed = _integer(0, "a non-negative integer")  # noise and simulate seeds
Positive = _number("a positive number", gt=0)
Fraction = _number("between 0 and 1", gt=0, lt=1)
Text = Annotated[str, Field(strict=True), _expect("a string")]


def _unit(label):
    try:
        return normalize_unit(label)
    except RecordError as exc:
        raise _problem(getattr(exc, "problem", str(exc))) from None


def _lag_range(spec):
    try:
        parse_range(spec)
    except ConfigError as exc:
        raise _problem(str(exc)) from None
    return spec  # kept as written; parse_range reads it where the range is used


def _listify(value):
    return [value] if isinstance(value, str) else value


def _roles(value, handler):
    try:
        return handler(value)
    except ValidationError as exc:
        errors = exc.errors()
        if all(e["type"] == "literal_error" and isinstance(e["input"], str) for e in errors):
            raise _problem(f"unknown role {errors[0]['input']!r}; roles are {', '.join(ROLES)}") from None
        raise _problem(f"must be a non-empty list of role names, got {value!r}") from None


def _window_order(w):
    if not 0 <= w[0] < w[1]:
        raise ValueError("t0 must be >= 0 and below t1")
    return w


def _array_of_tables(value, handler):
    if not isinstance(value, list) or not all(isinstance(r, dict) for r in value):
        raise _problem("must be an array of tables ([[records]])")
    return handler(value)


LagRange = Annotated[Any, AfterValidator(_lag_range)]
Roles = Annotated[list[Literal[ROLES]], BeforeValidator(_listify), Field(min_length=1), WrapValidator(_roles)]
Time = Annotated[float, Field(strict=True)]
Window = Annotated[tuple[Time, Time], Field(strict=False), AfterValidator(_window_order),
                   _expect("[t0, t1] in s with 0 <= t0 < t1")]
PathText = Annotated[str, Field(strict=True, pattern=r"\S"), _expect("a file or folder path string")]
RecordName = Annotated[str, Field(strict=True, pattern=r"\S"), _expect("a non-blank record name")]


# ============================================================================ tables
class _Table(BaseModel):
    """A TOML table: strict types; unknown keys kept unless a subclass forbids them."""

    model_config = ConfigDict(strict=True, extra="allow")
    #: what an unknown key is called in messages, and an example of the table for "must be a table like"
    noun: ClassVar[str] = "key"
    example: ClassVar[str] = ""
    #: optional keys that stay out of :meth:`as_dict` unless the config gives them
    omit_unset: ClassVar[tuple[str, ...]] = ()

    def as_dict(self) -> dict:
        """The table as the plain dict the pipeline reads: every key with its default filled in,
        then the unknown keys it kept."""
        d = self.model_dump()
        for k in self.omit_unset:
            if k not in self.model_fields_set:
                d.pop(k, None)
        return d

    @classmethod
    def defaults(cls) -> dict:
        """The optional keys and their defaults."""
        return {k: f.get_default(call_default_factory=True) for k, f in cls.model_fields.items()
                if not f.is_required() and k not in cls.omit_unset}


class _Closed(_Table):
    model_config = ConfigDict(strict=True, extra="forbid")


class UnitsTable(_Closed):
    """``system.units``: the unit labels of u and y (normalised spellings, "" when not given)."""

    example: ClassVar[str] = '{ u = "N", y = "m" }'
    u: Annotated[Any, AfterValidator(_unit)] = Field("", description="unit of the input u, e.g. N or V")
    y: Annotated[Any, AfterValidator(_unit)] = Field("", description="unit of the output y, e.g. m or m/s")


def _channel_names(value):
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v.strip() for v in value):
        raise _problem(f"must be a non-empty list of channel names, got {value!r}")
    if len(set(value)) != len(value):
        raise _problem(f"names a channel twice: {value!r}")
    if len(value) > MAX_CHANNELS:
        raise _problem(f"names {len(value)} channels; at most {MAX_CHANNELS}")
    return list(value)


ChannelNames = Annotated[Any, AfterValidator(_channel_names)]


class SystemTable(_Closed):
    omit_unset: ClassVar[tuple[str, ...]] = ("inputs", "outputs")
    fs: Positive = Field(description="sampling frequency in Hz")
    units: UnitsTable = Field(default_factory=UnitsTable, description="every record must match")
    output: _choice(OUTPUTS) = Field("displacement", description="what y is")
    inputs: ChannelNames | None = Field(None, description="the input channels by name, in order (default: the "
                                                          "record's own u)")
    outputs: ChannelNames | None = Field(None, description="the output channels by name, in order (default: the "
                                                           "record's own y; an LMS folder's laser)")


class PhysicsTable(_Closed):
    """Restoring force R = input_gain * u - mass * acceleration [N]."""

    mass: Positive | None = Field(None, description="modal mass [kg]")
    input_gain: Positive = Field(1.0, description="N per input unit (N/V for a shaker voltage)")


class ModelTable(_Closed):
    omit_unset: ClassVar[tuple[str, ...]] = ("ny", "nu")
    kernel: _choice(KERNELS) = Field("matern32+cubic", description="eq. 12")
    mode: _choice(MODES) = "exact"
    inducing: Count = Field(256, description="inducing points (sparse mode)")
    max_train_points: Count = Field(2000, description="training-point cap")
    selection: _choice(SELECTIONS) = Field("stride", description="rows for ML-II (resonance: sec. 4.2)")
    restarts: Index = Field(3, description="ML-II restarts")
    seed: Index = 0
    noise_calibration: _choice(NOISE_CALIBRATIONS) = "none"
    band_calibration: _choice(BAND_CALIBRATIONS) = "none"
    band_window: _number("a number of seconds in (0, 10]", gt=0, le=10) = Field(
        0.25, description="window of the band's local amplitude [s]")
    band_window_kind: _choice(BAND_WINDOW_KINDS) = Field(
        "centred", description="where that window lies: centred on each sample, or trailing (ending at it: a "
                               "stream's chunks then get the whole record's band)")
    band_hold: _number("a number of seconds in [0, 60]", ge=0, le=60) = Field(
        0.0, description="time constant of the held amplitude [s] (0: none): after a large response the band "
                         "keeps a share of its size, decaying by e every band_hold seconds")
    band_gp_scale: _choice(BAND_GP_SCALES) = Field(
        "fixed", description="the propagated band (eqs. 8-9) as it is (fixed), or multiplied by a factor "
                             "calibrated with the discrepancy scale on the 'lags' records (calibrated)")
    lengthscale_refine: _choice(LENGTHSCALE_REFINES) = Field(
        "none", description="ML-II's lengthscales as they are (none), or refined by free-run fit on the 'lags' "
                            "records (lags: training.hyper_refine)")
    lengthscale_refine_tolerance: _number("a number of points of fit in [0, 100]", ge=0, le=100) = Field(
        1.0, description="points of free-run fit a 'lags' record may lose against ML-II's lengthscales")
    ny: Count | None = Field(None, description="output lags (omit when chosen by the lag surface)")
    nu: Count | None = Field(None, description="input lags")
    hyper: _choice(("subset", "vfe")) = Field(
        "subset", description="sparse mode's hyperparameters: exact ML-II on the capped rows, or the VFE bound")


class PredictTable(_Closed):
    mc_paths: Count = Field(1024, description="Monte Carlo paths")
    confidence: Fraction = 0.99
    method: _choice(PREDICT_METHODS, "'mc' or 'linear'") = Field("mc", description="the report's free runs")


class NoveltyTable(_Closed):
    false_alarm_rate: Fraction = 0.01
    method: _choice(NOVELTY_METHODS, _one_of(NOVELTY_METHODS, quoted=False)) = NOVELTY_METHODS[0]


class NoiseTable(_Closed):
    """Output noise of variance ``fraction * mean(y_ref^2)``, y_ref the clean output of ``reference``."""

    example: ClassVar[str] = '{ fraction = 0.1, reference = "...", seed = 1 }'
    fraction: _number("a number >= 0", ge=0) = Field(
        description="noise variance over the mean square of the reference's clean output")
    reference: Annotated[str, Field(strict=True), _expect("a record name")] | None = Field(
        None, description="the record whose clean output sets the level (default: the record itself)")
    seed: Seed | None = None


class SimulateTable(_Closed):
    """A simulated record: the arguments of ``gpnarx simulate``. On load the names are checked; the
    values when the record is simulated (:class:`Simulation`)."""

    noun: ClassVar[str] = "option"
    example: ClassVar[str] = '{ system = "bouc-wen", ... }'
    system: _choice(SIM_SYSTEMS, _one_of(SIM_SYSTEMS, quoted=False)) = Field(description=" or ".join(SIM_SYSTEMS))
    excitation: _choice(SIM_EXCITATIONS, _one_of(SIM_EXCITATIONS, quoted=False)) = "sweep"
    amplitude: Any = Field(description="peak for sweep/sine, RMS for multisine/noise")
    f0: Any = None
    f1: Any = None
    rate: Any = None
    freq: Any = None
    duration: Any = None
    seed: Any = None
    torque: Any = None
    scatter: Any = None


_Above0 = _number("a finite number > 0", gt=0)


class Simulation(SimulateTable):
    """A ``simulate`` table as ``simulate_record`` runs it: amplitude in the system's input unit
    (N or V), f0/f1/freq [Hz], rate [Hz/s], duration [s], torque [N m] (stand-in only), scatter
    (stand-in only, 1 = calibrated default); only the options the excitation uses."""

    amplitude: _Above0 = Field(description="peak for sweep/sine, RMS for multisine/noise")
    f0: _number("a finite number >= 0", ge=0) | None = None
    f1: _Above0 | None = None
    rate: _Above0 | None = None
    freq: _Above0 | None = None
    duration: _Above0 | None = None
    seed: Seed | None = None
    torque: _Above0 | None = None
    scatter: _number("between 0 and 100 (1 = calibrated default)", ge=0, le=100) | None = None

    @model_validator(mode="before")
    @classmethod
    def _options_apply(cls, data):
        if not isinstance(data, dict):
            return data
        system, exc = data.get("system"), data.get("excitation", "sweep")
        if system not in SIM_SYSTEMS or exc not in SIM_EXCITATIONS:
            return data  # the fields say so
        for key in ("torque", "scatter"):
            if key in data and system != "bert-standin":
                raise _problem(f"{key} applies only to bert-standin")
        for key in SIM_OPTIONS:
            if key in data and key not in specs.USES[exc]:
                raise _problem(f"{key} does not apply to excitation {exc}")
        return data


class RecordTable(_Closed):
    name: RecordName = Field(description="a unique record name")
    roles: Roles = Field(description='e.g. roles = ["train"]')
    path: PathText | None = Field(None, description="a record file or LMS folder, relative to the config's folder")
    simulate: SimulateTable | None = None
    noise: NoiseTable | None = None
    window: Window | None = Field(None, description="[t0, t1] in s, start inclusive, end exclusive")
    fs: Positive | None = Field(None, description="sampling frequency in Hz of a file that stores none")
    meta: dict = Field(default_factory=dict, description="free metadata, copied into Record.meta")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.path is None) == (self.simulate is None):
            raise _problem("give exactly one of path or simulate")
        return self


class DatasetDoc(_Table):
    """The whole document; unknown top-level keys are kept (``DatasetConfig.extra``)."""

    name: Annotated[str, Field(strict=True, pattern=NAME_PATTERN),
                    _expect("a name of letters, digits, '.', '_' or '-'")] = Field(description="bundle name")
    description: Text = ""
    system: SystemTable = Field(default_factory=dict, validate_default=True)
    physics: PhysicsTable = Field(default_factory=PhysicsTable)
    model: ModelTable = Field(default_factory=ModelTable)
    lags: dict[str, LagRange] = Field(default_factory=dict, description="lag-surface ranges LO:HI[:STEP]")
    predict: PredictTable = Field(default_factory=PredictTable)
    novelty: NoveltyTable = Field(default_factory=NoveltyTable)
    records: Annotated[list[RecordTable], WrapValidator(_array_of_tables)] = Field(
        description="at least one [[records]] table with role 'train'")

    @model_validator(mode="after")
    def _across_records(self):
        names = set()
        for r in self.records:
            if r.name in names:
                raise _problem("duplicate record name", f"records.{r.name}")
            names.add(r.name)
        for r in self.records:
            if r.noise is not None and r.noise.reference is not None and r.noise.reference not in names:
                raise _problem(f"no record named {r.noise.reference!r}", f"records.{r.name}.noise.reference")
        if not any("train" in r.roles for r in self.records):
            raise _problem("no record has role 'train'", "records")
        for key in ("noise_calibration", "band_calibration", "lengthscale_refine"):
            if getattr(self.model, key) != "lags":
                continue
            held = [r for r in self.records if "lags" in r.roles]
            if not held:
                raise _problem("'lags' needs at least one record with role 'lags' (held out from training)",
                               f"model.{key}")
            for r in held:
                if "train" in r.roles:
                    raise _problem(f"a 'lags' record calibrates the band (model.{key} = 'lags') and must not "
                                   "also have role 'train'", f"records.{r.name}.roles")
        return self


# ============================================================================ messages
def _model_in(annotation) -> type[BaseModel] | None:
    """The model class inside a field's annotation (``X``, ``X | None``, ``list[X]``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _walk(root: type[BaseModel], loc) -> tuple[type[BaseModel] | None, Any]:
    """(the model holding the last key of ``loc``, that key's FieldInfo or None)."""
    model, info = root, None
    for part in loc:
        if isinstance(part, int):
            continue
        if model is None or part not in model.model_fields:
            return None, None
        info = model.model_fields[part]
        holder, model = model, _model_in(info.annotation)
    return (holder if info is not None else root), info


def _key(loc, doc, root: type[BaseModel]) -> str:
    """Dotted key of ``loc``; a record is named by its name when it has a valid one."""
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            name = None
            if root is DatasetDoc and loc[:i] == ("records",) and isinstance(doc, dict):
                rec = doc["records"][part]
                name = rec.get("name") if isinstance(rec, dict) else None
            out += f".{name}" if isinstance(name, str) and name.strip() else f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def explain(exc: ValidationError, doc, root: type[BaseModel] = DatasetDoc,
            missing: str = "missing required key") -> tuple[str, str]:
    """``(dotted key, problem)`` of the first error of ``exc`` (raised validating ``doc`` with
    ``root``). ``missing``: how a missing key is said ("missing required key", or "is required")."""
    errors = exc.errors()
    err = errors[0]
    loc, kind = tuple(err["loc"]), err["type"]
    if kind == "config":
        rel = err["ctx"].get("key", "")
        key = _key(loc, doc, root)
        return (f"{key}.{rel}" if key and rel else key or rel), err["ctx"]["problem"]
    if kind == "missing":
        _, info = _walk(root, loc)
        hint = f" ({info.description})" if info is not None and info.description else ""
        return _key(loc, doc, root), f"{missing}{hint}"
    if kind == "extra_forbidden":
        parent = loc[:-1]
        unknown = sorted(str(e["loc"][-1]) for e in errors if e["type"] == kind and tuple(e["loc"][:-1]) == parent)
        holder, info = _walk(root, parent)
        table = _model_in(info.annotation) if info is not None else holder
        allowed = sorted(table.model_fields) if table is not None else []
        noun = table.noun if table is not None and issubclass(table, _Table) else "key"
        return _key(parent, doc, root), f"unknown {noun}(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        _, info = _walk(root, loc)
        table = _model_in(info.annotation) if info is not None else None
        like = f" like {table.example}" if table is not None and issubclass(table, _Table) and table.example else ""
        return _key(loc, doc, root), f"must be a table{like}, got {type(err['input']).__name__}"
    return _key(loc, doc, root), f"{err['msg'][:1].lower()}{err['msg'][1:]}, got {err.get('input')!r}"
