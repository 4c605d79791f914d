"""What the three operations share: the request, its bounds and refusals, the plan and the free run.

``Operation`` is one operation (``predict``, ``loops``, ``novelty``: one subclass each, in a module of its own,
and the table ``run.OPERATIONS`` by name):

- ``Operation.plan(req, bundle, limits)``: cheap checks of a request against the bundle and the bounds
  (fs, lengths, y0, start, Monte Carlo paths and work, backend, stream state; an operation adds its own in
  ``validate``), before any work is queued.
- ``Operation.compute(plan, req)``: the free run (with the operation's ``run_options``) and the operation's
  ``answer`` derived from it; returns an ``Answer`` whose ``body`` is the operation's answer (a dict of numpy
  arrays, floats, strings and lists, the HTTP JSON answer).

``req`` is anything with the record fields of the HTTP body (``Request`` here, or the service's pydantic
``RecordRequest``): ``u`` [input units], ``fs`` [Hz], ``y`` [output units] or None, ``y0`` or None,
``mc_paths``, ``seed``, ``confidence``, ``method``, ``backend``, ``start``, ``state`` and ``return_state``.

Every refusal is an ``OperationError`` naming the field, the reason and a ``kind``: ``invalid`` (the request
does not fit the model or the bounds' rules: HTTP 422, CLI exit code 1), ``too_large`` (a size bound: 413)
or ``conflict`` (the model cannot do it, or a stream state belongs to another model: 409). The service turns
it into a problem detail (``service.problems``), the CLI into one line on stderr (``cli.errors``).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, ClassVar

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.backend import default_backend, jax_available
from gpnarx.model.envelope import assess, out_of_range
from gpnarx.model.freerun import FreeRunState, check_state
from gpnarx.model.gaps import GapError, check_gaps
from gpnarx.model.novelty import novelty_start
from gpnarx.model.record import FS_RTOL, fs_matches, resample_advice

from .stream_token import StateMismatch, StateTokenError, decode_state, encode_state, max_state_bytes

INVALID, TOO_LARGE, CONFLICT = "invalid", "too_large", "conflict"


class OperationError(ValueError):
    """A request the operation refuses: ``detail`` (one line), ``field`` (the request field to blame, or None),
    ``kind`` (``invalid``, ``too_large`` or ``conflict``), ``limit`` (the bound exceeded, or None) and
    ``extra`` (more members for the problem detail, e.g. ``model_fs``)."""

    def __init__(self, detail: str, field: str | None = None, *, kind: str = INVALID, limit: Any = None,
                 **extra: Any):
        super().__init__(detail)
        self.detail = detail
        self.field = field
        self.kind = kind
        self.limit = limit
        self.extra = extra


@dataclass(frozen=True)
class Limits:
    """The bounds a plan is checked against (None: unbounded). The service's come from its settings
    (``GPNARX_MAX_SAMPLES`` ...), the CLI's leave sizes unbounded.

    max_samples: samples per record; mc_paths_default: Monte Carlo paths when the request names none (None:
    the model's own, ``default_mc_paths``; the service sets it only from ``GPNARX_MC_PATHS_DEFAULT``);
    mc_paths_max: Monte Carlo paths per record; max_mc_work: Monte Carlo path-steps (paths x samples) per
    request; backend: array backend when the request names none; stream_key: the secret that signs stream
    state tokens (None: a checksum only).
    """

    max_samples: int | None = None
    mc_paths_default: int | None = None
    mc_paths_max: int | None = None
    max_mc_work: int | None = None
    backend: str = "numpy"
    stream_key: str | None = None

    @classmethod
    def from_env(cls) -> Limits:
        """The bounds of a process without service settings (the CLI): the Monte Carlo path bound
        (``mc_paths_max``: ``GPNARX_MC_PATHS_MAX``, the service's too) and the default backend
        (``GPNARX_BACKEND``); sizes and work unbounded. A ValueError names an unusable variable."""
        return cls(mc_paths_max=mc_paths_max(), backend=default_backend())


#: Monte Carlo paths of a bundle whose manifest states none (training.config_schema's ``[predict] mc_paths``)
DEFAULT_MC_PATHS = 1024
#: Monte Carlo paths per record: the product's one bound, the HTTP service's ``mc_paths`` (its setting
#: ``GPNARX_MC_PATHS_MAX``) and the CLI's ``--mc`` alike; ``MC_PATHS_MAX_ENV`` raises or lowers it for both
MC_PATHS_MAX = 4096
MC_PATHS_MAX_ENV = "GPNARX_MC_PATHS_MAX"


def mc_paths_max(environ=None) -> int:
    """The Monte Carlo path bound in force: ``GPNARX_MC_PATHS_MAX`` when set (an integer >= 1; a ValueError naming
    it otherwise), else ``MC_PATHS_MAX``."""
    from gpnarx.runtime import env_int

    return env_int(MC_PATHS_MAX_ENV, MC_PATHS_MAX, environ, minimum=1)


@dataclass(frozen=True)
class Request:
    """A record request (the HTTP body's fields): u [input units], fs [Hz], y [output units] or None,
    y0 (initial outputs) or None."""

    u: Any
    fs: float
    y: Any = None
    y0: Any = None
    mc_paths: int | None = None
    seed: int = 0
    confidence: float = 0.99
    method: str | None = None
    backend: str | None = None
    start: str | None = None
    state: str | None = None
    return_state: bool = False
    horizon: int | None = None


@dataclass(frozen=True)
class Plan:
    operation: str
    bundle: Any
    method: str
    mc_paths: int  # 0 for linear
    work: int  # Monte Carlo path-steps (samples for linear)
    backend: str = "numpy"  # array backend of the free run (model.backend)
    state: FreeRunState | None = None  # the stream state the free run continues (request's `state`)
    stream_key: str | None = None  # signs the answer's state token
    horizon: int | None = None  # k of a k-step-ahead prediction (request's `horizon`; model.freerun.horizon)
    gaps: tuple = ()  # the record's gaps, (start, end) samples (model.gaps)


@dataclass
class Answer:
    """An operation's outcome: ``body`` (the answer), ``path_steps`` (Monte Carlo path-steps done, 0 for a
    linearised run), ``run`` (the free run itself, ``model.freerun.FreeRun``) and ``metrics`` (``metrics.summary``
    of the measured y against the band, or None without y)."""

    body: dict
    path_steps: int
    run: Any
    metrics: dict | None = field(default=None)


def _given(a) -> bool:
    return a is not None and len(a) > 0


def check_fs(fs, bundle) -> float:
    """The one sampling-frequency rule of every interface (HTTP routes, batch, CLI commands): ``fs`` [Hz] of a
    record against ``bundle.fs``. Within ``FS_RTOL`` the model's fs is returned (the record is taken at the
    model's rate); otherwise an ``OperationError`` on ``fs`` naming both rates, the tolerance and how to resample
    (``limit``: ``FS_RTOL``; ``model_fs``: the model's rate)."""
    fs = float(fs)
    if fs_matches(fs, bundle.fs):
        return float(bundle.fs)
    raise OperationError(f"fs {fs:.12g} Hz does not match the model's fs {bundle.fs:.12g} Hz "
                         f"({bundle.name}:{bundle.version}; tolerance {FS_RTOL * 1e6:g} ppm): "
                         f"{resample_advice(fs, bundle.fs)}", "fs", limit=FS_RTOL, model_fs=bundle.fs)




class Operation:
    """One operation on a loaded bundle. A subclass names itself (``name``) and gives what is its own: the
    checks of a request beyond the record's (``validate``), the options of its free run (``run_options``) and
    its answer (``answer``); ``plan`` and ``compute`` are the same for every operation.

    ``start``: the start rule of a request that names none and sends no y0 ('rest', or 'measured': from the
    record's first ny outputs); ``mc_paths_from``: the manifest sections whose ``mc_paths`` give the default
    Monte Carlo paths, first found wins (``default_mc_paths``).
    """

    name: ClassVar[str]
    start: ClassVar[str] = "rest"
    mc_paths_from: ClassVar[tuple[str, ...]] = ("predict",)

    # ---------------------------------------------------------------- what an operation gives
    def validate(self, req, bundle) -> None:
        """The operation's own checks of ``req`` against ``bundle`` (an ``OperationError`` to refuse it)."""

    def check_bundle(self, bundle) -> None:
        """Whether ``bundle`` can do this operation at all (an ``OperationError``, kind ``conflict``, if not)."""

    def run_options(self, plan: Plan, req, u: np.ndarray) -> dict:
        """Extra keyword arguments of the free run (``GPNARX.simulate``)."""
        return {}

    def answer(self, plan: Plan, req, u: np.ndarray, y: np.ndarray | None, run, common: dict, flags: dict,
               checkpoint: Callable[[], None] | None) -> tuple[dict, dict | None, dict | None]:
        """(answer body, ``metrics.summary`` of y against the band or None, what a stream carries to its next
        chunk or None) of the free run ``run``; ``common``: the members every answer holds."""
        raise NotImplementedError

    # ---------------------------------------------------------------- the same for every operation
    def default_mc_paths(self, bundle) -> int:
        """Monte Carlo paths of an answer whose request names none: the one rule of the CLI, the HTTP service
        (predict, loops, novelty, batch), the /ui page (it sends none) and GET /v1/models/NAME.

        ``bundle``: a loaded bundle (anything with ``manifest``) or a manifest dict. The first of the manifest's
        ``mc_paths_from`` sections with ``mc_paths`` > 0 (novelty: the paths its threshold was calibrated with,
        ``novelty.mc_paths``, so a score is compared with scores of its own kind; then the trained config's
        ``[predict] mc_paths``, ``predict.mc_paths``); ``DEFAULT_MC_PATHS`` for a bundle that states none.
        """
        manifest = bundle if isinstance(bundle, dict) else (getattr(bundle, "manifest", None) or {})
        for key in self.mc_paths_from:
            section = manifest.get(key)
            if not isinstance(section, dict):
                continue
            try:
                paths = int(section.get("mc_paths") or 0)
            except (TypeError, ValueError):
                continue
            if paths > 0:
                return paths
        return DEFAULT_MC_PATHS

    def start_of(self, req) -> str:
        """The request's start rule: 'state' when it continues a stream, its ``start`` field, else 'measured'
        when it sends y0, and the operation's ``start`` otherwise."""
        if getattr(req, "state", None) is not None:
            return "state"
        start = getattr(req, "start", None)
        if start is not None:
            return start
        return "measured" if self.start == "measured" or _given(getattr(req, "y0", None)) else "rest"

    def plan(self, req, bundle, limits: Limits, budget: int | None = None) -> Plan:
        """Check ``req`` against ``bundle`` (a loaded Bundle: name, version, fs [Hz], model, manifest) and
        ``limits``; ``budget``: Monte Carlo path-steps left to this request (a batch's shared budget)."""
        seed = getattr(req, "seed", 0)
        if not is_int(seed, 0, 2**63 - 1):
            raise OperationError(f"seed must be an integer in [0, 2^63), got {str(seed)[:40]}", "seed")
        n = len(req.u)
        if limits.max_samples is not None and n > limits.max_samples:
            raise OperationError(f"u has {n} samples; the limit is {limits.max_samples} samples per record", "u",
                                 kind=TOO_LARGE, limit=limits.max_samples)
        check_fs(req.fs, bundle)  # within FS_RTOL: the free run and what is derived from it use the model's fs
        if req.y is not None and len(req.y) != n:
            raise OperationError(f"y has {len(req.y)} samples but u has {n}; they must have the same length", "y")
        gaps = self.check_gaps(req, bundle)
        horizon = self.check_horizon(req, bundle)
        self.validate(req, bundle)
        ny = bundle.model.ny
        if _given(req.y0):
            if len(req.y0) < ny:
                raise OperationError(f"y0 must hold at least ny={ny} initial outputs for this model, got "
                                     f"{len(req.y0)}", "y0")
            if n <= ny:
                raise OperationError(f"u must be longer than ny={ny} samples when y0 is given, got {n}", "u")
        if getattr(req, "start", None) == "rest" and _given(req.y0):
            raise OperationError("start 'rest' and y0 contradict each other: y0 starts the free run from measured "
                                 "outputs; leave y0 out to start at rest, or send start 'measured'", "start")
        if self.start_of(req) == "measured" and req.y is None and not _given(req.y0):
            raise OperationError(f"start 'measured' needs the record's measured output: send y (its first ny={ny} "
                                 f"samples start the free run) or y0", "start")
        self.check_bundle(bundle)
        method = req.method or bundle.default_method(self.name)
        if method == "mc":
            paths, work = _mc_work(req, n, limits, budget, self.default_mc_paths(bundle))
        else:
            paths, work = 0, n
        backend = req.backend or limits.backend
        if backend == "jax" and not jax_available():
            raise OperationError("backend 'jax' is not installed here (pip install 'gpnarx[jax]'); use backend "
                                 "'numpy'", "backend")
        state = _stream_state(req, bundle, limits, method, paths, backend)
        if horizon is not None and backend != "numpy":
            raise OperationError(f"horizon: a k-step prediction runs on the numpy backend; send backend 'numpy' "
                                 f"(got '{backend}')", "horizon")
        return Plan(self.name, bundle, method, paths, work, backend, state, limits.stream_key, horizon, tuple(gaps))

    # ---------------------------------------------------------------- k-step prediction and gaps
    #: whether the operation takes records with gaps and a horizon (predict does; loops and novelty need a whole,
    #: gap-free free run)
    takes_gaps: ClassVar[bool] = False

    def check_gaps(self, req, bundle) -> list:
        """The record's gaps (``model.gaps``: null / NaN runs in u or y), checked against the limits; an
        ``OperationError`` naming the field where the operation cannot take them, a stream carries them, or a
        limit is passed."""
        u = _series_with_gaps(req.u)
        y = None if req.y is None else _series_with_gaps(req.y)
        if _given(getattr(req, "y0", None)):
            if not np.all(np.isfinite(_series_with_gaps(req.y0))):
                raise OperationError("y0 must hold finite numbers (a measured start has no gap)", "y0")
        miss = np.isnan(u) | (np.isnan(y) if y is not None else False)
        if not np.any(miss):
            return []
        field = "u" if np.isnan(u).any() else "y"
        if not self.takes_gaps:
            raise OperationError(f"{field} holds gaps (null or NaN samples); {self.name} needs a gap-free record "
                                 f"(predict takes records with gaps)", field)
        if getattr(req, "state", None) is not None or getattr(req, "return_state", False):
            raise OperationError(f"{field} holds gaps (null or NaN samples): a stream cannot carry a record with "
                                 "gaps; send the record whole, without state", field)
        try:
            return check_gaps(u, y, float(bundle.fs))
        except GapError as exc:
            raise OperationError(str(exc), exc.field, limit=exc.limit) from None

    def check_horizon(self, req, bundle) -> int | None:
        """The request's ``horizon`` (k of a k-step-ahead prediction), checked: an integer >= 1, predict only, with
        y, not in a stream. None without one."""
        k = getattr(req, "horizon", None)
        if k is None:
            return None
        if not is_int(k, 1):
            raise OperationError(f"horizon must be an integer >= 1 (samples between restarts from the measured "
                                 f"outputs), got {str(k)[:40]}", "horizon", limit=1)
        if not self.takes_gaps:
            raise OperationError(f"horizon: {self.name} answers for the free run; a k-step prediction is predict's",
                                 "horizon")
        if req.y is None:
            raise OperationError("horizon: a k-step prediction restarts from the measured outputs every k samples; "
                                 "send the record's measured output y", "y")
        if getattr(req, "state", None) is not None or getattr(req, "return_state", False):
            raise OperationError("horizon: a stream cannot carry a k-step prediction (it restarts from measured "
                                 "outputs every k samples); send the record whole, without state or return_state",
                                 "horizon")
        if _given(req.y0) or getattr(req, "start", None) is not None:
            raise OperationError("horizon: a k-step prediction starts from y's first ny samples; y0 and start do not "
                                 "apply (leave them out)", "horizon")
        if len(req.u) <= bundle.model.ny:
            raise OperationError(f"u must be longer than ny={bundle.model.ny} samples for a k-step prediction, got "
                                 f"{len(req.u)}", "u")
        return int(k)

    def compute(self, plan: Plan, req, *, progress: Callable | None = None,
                checkpoint: Callable[[], None] | None = None) -> Answer:
        """Run the planned operation on ``req``.

        progress: ``progress(done, total)`` from the free run (samples); checkpoint: called between the stages
        (a cancellation point: whatever it raises ends the operation).
        """
        if checkpoint is not None:
            checkpoint()
        b = plan.bundle
        u = _series_with_gaps(req.u)
        run = self._simulate(plan, req, u, progress)
        if plan.gaps:  # the flags of what was measured and predicted
            keep = ~np.isnan(run.mean)
            y_kept = None if req.y is None else _series_with_gaps(req.y)[keep]
            flags = assess(getattr(b.model, "envelope_", None),
                           SimpleNamespace(method=run.method, diverged_paths=run.diverged_paths, mean=run.mean[keep]),
                           u[keep], y_kept)
        else:
            flags = assess(getattr(b.model, "envelope_", None), run, u, req.y)
        common = {"confidence": float(run.confidence), "mc_paths": int(run.n_paths), "method": run.method,
                  "backend": run.backend, "seed": int(req.seed), "start": self.started(plan, req), **flags}
        steps = int(run.path_steps) if run.method == "mc" else 0
        y = None if req.y is None else _series_with_gaps(req.y)
        body, metrics, carry = self.answer(plan, req, u, y, run, common, flags, checkpoint)
        body.update(_stream_fields(plan, req, run, carry))
        return Answer(body, steps, run, metrics)

    def started(self, plan: Plan, req) -> str:
        """How the free run actually started, as an answer's ``start`` says it: 'state' (a stream's later chunk),
        'measured' (from y0 or y's first ny samples) or 'rest' (also a 'measured' request whose y is not longer
        than ny samples: nothing is left to start from)."""
        if plan.state is not None:
            return "state"
        return "measured" if self.initial_outputs(plan, req) is not None else "rest"

    def initial_outputs(self, plan: Plan, req):
        """y0 of the free run: the record's measured start, a request's y0, or None (rest, or a stream's state)."""
        if self.start_of(req) == "measured":
            y0 = novelty_start(req.y if req.y is not None else [], plan.bundle.model.ny, req.y0)
            if y0 is not None and plan.gaps and np.isnan(np.asarray(y0, dtype=float)).any():
                return None  # a gap in the first ny samples: the pieces after it start from measured outputs
            return y0
        if plan.state is not None:
            return None
        return req.y0 if _given(req.y0) else None

    def culprit(self, plan: Plan, req, u: np.ndarray, head: str) -> tuple[str, str]:
        """(message, field) of an answer that came out non-finite: the measured start (``y0``, or ``y``'s first
        ny samples) when it lies beyond the trained output range and u does not lie beyond the input range,
        else u."""
        env = getattr(plan.bundle.model, "envelope_", None)
        y_start = self.initial_outputs(plan, req)
        flags = out_of_range(env, u, y_start) if y_start is not None else []
        if "y" in flags and "u" not in flags:
            field = "y0" if _given(req.y0) else "y"
            where = "y0" if field == "y0" else f"the first ny={plan.bundle.model.ny} samples of y (the measured start)"
            return (head + f"{where} lie far outside the output range the model was trained on (peak "
                           f"{env['y_peak']:.4g}); check their unit and scale", field)
        return (head + "u is probably far outside the amplitude or frequency range the model was trained on", "u")

    def _simulate(self, plan: Plan, req, u: np.ndarray, progress: Callable | None):
        model = plan.bundle.model
        try:
            with np.errstate(all="ignore"):
                stream = {"state": plan.state, "open_end": bool(getattr(req, "return_state", False))}
                if plan.gaps or plan.horizon is not None:  # y: where the run restarts (model.gaps, freerun.horizon)
                    stream.update(y=None if req.y is None else _series_with_gaps(req.y), horizon=plan.horizon)
                run = model.simulate(u, n_paths=max(plan.mc_paths, 1), seed=int(req.seed),
                                     y0=self.initial_outputs(plan, req), confidence=float(req.confidence),
                                     method=plan.method, backend=plan.backend, progress=progress,
                                     **self.run_options(plan, req, u), **stream)
        except np.linalg.LinAlgError:  # a factorisation of non-finite numbers (a ValueError too): the run diverged
            raise OperationError(*self._diverged(plan, req, u)) from None
        except ValueError as exc:
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else "invalid record"
            raise OperationError(msg, _field_from_message(msg)) from None
        keep = ~np.isnan(run.mean) if plan.gaps else slice(None)  # a gap's NaN is the answer's, not a divergence
        if not (np.all(np.isfinite(run.mean[keep])) and np.all(np.isfinite(run.lower[keep]))
                and np.all(np.isfinite(run.upper[keep])) and np.all(np.isfinite(run.std[keep]))):
            raise OperationError(*self._diverged(plan, req, u))
        return run

    def _diverged(self, plan: Plan, req, u: np.ndarray) -> tuple[str, str]:
        """(message, field) of a free run that gave non-finite outputs (``culprit``)."""
        head = (f"the free-run prediction of {plan.bundle.name}:{plan.bundle.version} diverged for this input "
                "(non-finite outputs): ")
        return self.culprit(plan, req, u, head)


def _series_with_gaps(a) -> np.ndarray:
    """A record series as float64, a gap's null (None) as NaN."""
    try:
        return np.asarray(a, dtype=float)
    except TypeError:  # a list holding None
        return np.array([np.nan if v is None else v for v in a], dtype=float)


def mc_paths_of(requested, limits: Limits, model_default: int) -> int:
    """The Monte Carlo paths of a request, the one rule of every front end: ``requested`` (the request's
    ``mc_paths``, the CLI's ``--mc``), else ``limits.mc_paths_default``, else ``model_default`` (the bundle's
    ``default_mc_paths``); an ``OperationError`` on ``mc_paths`` unless it is at least 1 and at most
    ``limits.mc_paths_max``."""
    paths = requested if requested is not None else (
        limits.mc_paths_default if limits.mc_paths_default is not None else model_default)
    paths = int(paths)
    if paths < 1:
        raise OperationError(f"mc_paths must be at least 1, got {paths}", "mc_paths")
    if limits.mc_paths_max is not None and paths > limits.mc_paths_max:
        what = "" if requested is not None else " (the model's default; send fewer)"
        raise OperationError(f"mc_paths {paths}{what} exceeds the limit of {limits.mc_paths_max} Monte Carlo paths",
                             "mc_paths", limit=limits.mc_paths_max)
    return paths


def _mc_work(req, n: int, limits: Limits, budget: int | None, model_default: int) -> tuple[int, int]:
    """(Monte Carlo paths, path-steps) of a request (``mc_paths_of``), checked against the work bounds."""
    paths = mc_paths_of(req.mc_paths, limits, model_default)
    work = paths * n
    limit = limits.max_mc_work if budget is None else budget
    if limit is not None and work > limit:
        what = ("the Monte Carlo work limit" if budget is None
                else "the Monte Carlo work left in this batch's budget")
        raise OperationError(f"mc_paths x samples = {paths} x {n} = {work} path-steps exceeds {what} "
                             f"({limit}; at most {limits.max_mc_work} per request); send fewer paths or "
                             f"a shorter record", "mc_paths", kind=TOO_LARGE, limit=limit)
    return paths, work


def _stream_state(req, bundle, limits: Limits, method: str, paths: int, backend: str):
    """The request's stream state, decoded and checked against this call (None without one)."""
    token = getattr(req, "state", None)
    if getattr(req, "return_state", False) and backend != "numpy":
        raise OperationError(f"backend '{backend}' cannot return a stream state; send backend 'numpy'",
                             "return_state")
    if token is None:
        return None
    model = bundle.model
    window = (getattr(model, "band_discrepancy_", None) or {}).get("window") or 0
    largest = max_state_bytes(model.ny, model.nu, bundle.fs, paths if method == "mc" else 0, window)
    try:
        state = decode_state(token, bundle.name, bundle.version, limits.stream_key, max_bytes=largest)
    except StateMismatch as exc:
        raise OperationError(str(exc), "state", kind=CONFLICT) from None
    except StateTokenError as exc:
        raise OperationError(str(exc), "state", limit=exc.limit) from None
    try:  # the model's own rule (method, paths, lags), checked here before the call queues
        check_state(state, method, bundle.model.ny, bundle.model.nu, None, paths)
    except ValueError as exc:
        raise OperationError(str(exc), "state") from None
    if backend != "numpy":
        raise OperationError("a stream (state) continues on the numpy backend only; send backend 'numpy'",
                             "backend")
    if _given(req.y0) or getattr(req, "start", None) is not None:
        raise OperationError("state continues a free run: y0 and start do not apply (leave them out)", "state")
    return state


_FIELD_RE = re.compile(r"^(u|y0|y|fs|confidence|n_paths|mc_paths|method|seed|horizon|state)\b")


def _field_from_message(msg: str) -> str | None:
    m = _FIELD_RE.match(msg)
    if not m:
        return None
    return {"n_paths": "mc_paths"}.get(m.group(1), m.group(1))


def is_stream(plan: Plan, req) -> bool:
    """A call of a stream: it continues a state, or asks for one."""
    return plan.state is not None or bool(getattr(req, "return_state", False))


def carried(plan: Plan, key: str) -> dict | None:
    """What the request's state carries for operation ``key`` (None: nothing, or no state)."""
    return ((plan.state.carry or {}).get(key)) if plan.state is not None else None


def _stream_fields(plan: Plan, req, run, carry: dict | None = None) -> dict:
    """The answer's stream members: the end state's token (with what the operation carries to the next chunk,
    ``carry``) when asked for, and the stream position."""
    if not is_stream(plan, req):
        return {}
    out = {"stream_position": int(run.state.position)}  # plan: streams run on numpy, which returns a state
    if getattr(req, "return_state", False):
        run.state.carry = {plan.operation: carry} if carry else None
        out["state"] = encode_state(run.state, plan.bundle.name, plan.bundle.version, plan.stream_key)
    return out


def finite_or_none(v) -> float | None:
    """``v`` as a float, None when it is not finite (JSON has no NaN)."""
    v = float(v)
    return v if math.isfinite(v) else None


def head(b) -> dict:
    """The members that name the model of every answer."""
    return {"model": b.name, "version": b.version}
