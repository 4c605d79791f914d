"""The three operations (predict, loops, novelty) on a loaded bundle, without any web framework.

``plan`` runs on the event loop: cheap checks of a validated request against the bundle and the
bounds (fs, lengths, y0, Monte Carlo paths and work), raising ``ProblemError`` naming the field
and the limit. ``compute`` runs on a worker thread: the free run and what is derived from it.
Answers are plain dicts of numpy arrays and floats (serialised by ``service.app``).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from gpnarx.model.backend import jax_available
from gpnarx.model.cycles import cov_window_for, cycles
from gpnarx.model.envelope import assess
from gpnarx.model.freerun_core import FreeRunState, check_state
from gpnarx.model.metrics import summary
from gpnarx.model.novelty import UnusableProbeContract, assess_novelty, novelty_start
from gpnarx.model.restoring import loop_area, loop_units, restoring_force
from gpnarx.model.stream_token import StateMismatch, StateTokenError, decode_state, encode_state
from gpnarx.storage.bundle import Bundle

from .problems import ProblemError
from .settings import Settings
from .worker import CancelToken

OPERATIONS = ("predict", "loops", "novelty")


@dataclass(frozen=True)
class Plan:
    operation: str
    bundle: Bundle
    method: str
    mc_paths: int  # 0 for linear
    work: int  # Monte Carlo path-steps (samples for linear)
    backend: str = "numpy"  # array backend of the free run (model.backend)
    state: FreeRunState | None = None  # the stream state the free run continues (request's `state`)
    stream_key: str | None = None  # signs the answer's state token (settings.stream_key)


def _fs_matches(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


def plan(operation: str, req, bundle: Bundle, settings: Settings, budget: int | None = None) -> Plan:
    """Check ``req`` (a validated RecordRequest) against ``bundle`` and the bounds."""
    n = len(req.u)
    if n > settings.max_samples:
        raise ProblemError(413, f"u has {n} samples; the limit is {settings.max_samples} samples per record",
                           "u", limit=settings.max_samples)
    if not _fs_matches(float(req.fs), bundle.fs):
        raise ProblemError(422, f"fs {req.fs:g} Hz does not match the model's fs {bundle.fs:g} Hz "
                                f"({bundle.name}:{bundle.version}); resample the record to {bundle.fs:g} Hz",
                           "fs", model_fs=bundle.fs)
    if req.y is not None and len(req.y) != n:
        raise ProblemError(422, f"y has {len(req.y)} samples but u has {n}; they must have the same length", "y")
    if operation == "novelty" and req.y is None:
        raise ProblemError(422, "y is required for novelty: the measured output record to score", "y")
    ny = bundle.model.ny
    if req.y0 is not None and len(req.y0) > 0:
        if len(req.y0) < ny:
            raise ProblemError(422, f"y0 must hold at least ny={ny} initial outputs for this model, got "
                                    f"{len(req.y0)}", "y0")
        if n <= ny:
            raise ProblemError(422, f"u must be longer than ny={ny} samples when y0 is given, got {n}", "u")
    if start_of(operation, req) == "measured" and req.y is None and not req.y0:
        raise ProblemError(422, f"start 'measured' needs the record's measured output: send y (its first ny={ny} "
                                f"samples start the free run) or y0", "start")
    if operation == "loops":
        physics_of(bundle)
    if operation == "novelty":
        novelty_of(bundle)
    method = req.method or bundle.default_method(operation)
    if method == "mc":
        paths = settings.mc_paths_default if req.mc_paths is None else int(req.mc_paths)
        if paths > settings.mc_paths_max:
            raise ProblemError(422, f"mc_paths {paths} exceeds the limit of {settings.mc_paths_max} Monte Carlo "
                                    f"paths", "mc_paths", limit=settings.mc_paths_max)
        work = paths * n
        limit = settings.max_mc_work if budget is None else budget
        if work > limit:
            what = ("the Monte Carlo work limit" if budget is None
                    else "the Monte Carlo work left in this batch's budget")
            raise ProblemError(413, f"mc_paths x samples = {paths} x {n} = {work} path-steps exceeds {what} "
                                    f"({limit}; at most {settings.max_mc_work} per request); send fewer paths or "
                                    f"a shorter record", "mc_paths", limit=limit)
    else:
        paths, work = 0, n
    backend = req.backend or settings.backend
    if backend == "jax" and not jax_available():
        raise ProblemError(422, "backend 'jax' is not installed on this server (pip install 'gpnarx[jax]'); "
                                "use backend 'numpy'", "backend")
    state = _stream_state(req, bundle, settings, method, paths, backend)
    return Plan(operation, bundle, method, paths, work, backend, state, settings.stream_key)


def _stream_state(req, bundle: Bundle, settings: Settings, method: str, paths: int, backend: str):
    """The request's stream state, decoded and checked against this call (None without one)."""
    token = getattr(req, "state", None)
    if getattr(req, "return_state", False) and backend != "numpy":
        raise ProblemError(422, f"backend '{backend}' cannot return a stream state; send backend 'numpy'",
                           "return_state")
    if token is None:
        return None
    try:
        state = decode_state(token, bundle.name, bundle.version, settings.stream_key)
    except StateMismatch as exc:
        raise ProblemError(409, str(exc), "state") from None
    except StateTokenError as exc:
        raise ProblemError(422, str(exc), "state") from None
    try:  # the model's own rule (method, paths, lags), checked here before the call queues
        check_state(state, method, bundle.model.ny, bundle.model.nu, None, paths)
    except ValueError as exc:
        raise ProblemError(422, str(exc), "state") from None
    if backend != "numpy":
        raise ProblemError(422, "a stream (state) continues on the numpy backend only; send backend 'numpy'",
                           "backend")
    if (req.y0 is not None and len(req.y0) > 0) or getattr(req, "start", None) is not None:
        raise ProblemError(422, "state continues a free run: y0 and start do not apply (leave them out)", "state")
    return state


def start_of(operation: str, req) -> str:
    """The request's start rule: 'state' when it continues a stream, its ``start`` field, else 'measured' for
    novelty and 'rest' otherwise."""
    if getattr(req, "state", None) is not None:
        return "state"
    start = getattr(req, "start", None)
    return start if start is not None else ("measured" if operation == "novelty" else "rest")


def physics_of(bundle: Bundle) -> dict:
    phys = bundle.manifest.get("physics") or {}
    try:
        mass = float(phys["mass"])
    except (KeyError, TypeError, ValueError):
        raise ProblemError(409, f"model {bundle.name}:{bundle.version} has no physical constants (mass) for the "
                                f"restoring force; loops are not available for it") from None
    gain = phys.get("input_gain", 1.0)
    output = phys.get("output", "displacement")
    if not (mass > 0 and math.isfinite(mass)) or output not in ("displacement", "velocity"):
        raise ProblemError(409, f"model {bundle.name}:{bundle.version} has unusable physical constants "
                                f"(mass={mass!r}, output={output!r})")
    try:
        gain = float(gain)
    except (TypeError, ValueError):
        raise ProblemError(409, f"model {bundle.name}:{bundle.version} has an unusable input_gain") from None
    return {**{k: v for k, v in phys.items() if isinstance(v, (int, float, str, bool))},
            "mass": mass, "input_gain": gain, "output": output}


def novelty_of(bundle: Bundle) -> dict:
    nov = bundle.manifest.get("novelty")
    if not isinstance(nov, dict) or not isinstance(nov.get("threshold"), (int, float)):
        raise ProblemError(409, f"model {bundle.name}:{bundle.version} has no novelty calibration; train it with "
                                f"'healthy' records to get a threshold (the default bert-standin-monitor bundle has "
                                f"one)")
    return nov


_FIELD_RE = re.compile(r"^(u|y0|y|fs|confidence|n_paths|mc_paths|method|seed)\b")


def _field_from_message(msg: str) -> str | None:
    m = _FIELD_RE.match(msg)
    if not m:
        return None
    return {"n_paths": "mc_paths"}.get(m.group(1), m.group(1))


def _simulate(plan: Plan, req, token: CancelToken | None = None):
    u = np.asarray(req.u, dtype=float)
    model = plan.bundle.model
    if token is not None:
        token.check()
    try:
        with np.errstate(all="ignore"):
            if start_of(plan.operation, req) == "measured":
                y0 = novelty_start(req.y if req.y is not None else [], model.ny, req.y0)
            elif plan.state is not None:
                y0 = None
            else:
                y0 = req.y0 or None
            stream = {"state": plan.state, "open_end": bool(getattr(req, "return_state", False))}
            extra = {}
            if plan.operation == "loops":  # per-cycle energy intervals need every path / the covariance band
                extra = ({"keep_paths": True} if plan.method == "mc"
                         else {"cov_window": cov_window_for(u, plan.bundle.fs, model.ny)})
            run = model.simulate(u, n_paths=max(plan.mc_paths, 1), seed=int(req.seed), y0=y0,
                                 confidence=float(req.confidence), method=plan.method, backend=plan.backend,
                                 progress=None if token is None else token.progress, **extra, **stream)
    except ValueError as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else "invalid record"
        raise ProblemError(422, msg, _field_from_message(msg)) from None
    if not (np.all(np.isfinite(run.mean)) and np.all(np.isfinite(run.lower)) and np.all(np.isfinite(run.upper))
            and np.all(np.isfinite(run.std))):
        raise ProblemError(422, f"the free-run prediction of {plan.bundle.name}:{plan.bundle.version} diverged for "
                                f"this input (non-finite outputs): u is probably far outside the amplitude or "
                                f"frequency range the model was trained on", "u")
    return u, run


def _stream_fields(plan: Plan, req, run) -> dict:
    """The answer's stream members: the end state's token when asked for, and the stream position."""
    if plan.state is None and not getattr(req, "return_state", False):
        return {}
    out = {"stream_position": int(run.state.position)}  # plan: streams run on numpy, which returns a state
    if getattr(req, "return_state", False):
        out["state"] = encode_state(run.state, plan.bundle.name, plan.bundle.version, plan.stream_key)
    return out


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def compute(plan: Plan, req, token: CancelToken | None = None) -> tuple[dict, int]:
    """Run the operation; returns (answer dict, Monte Carlo path-steps done).

    ``token``: cooperative cancellation (deadline passed or client gone): ``worker.Cancelled`` is
    raised at the free run's next checkpoint (every 256 samples) once it is set.
    """
    b = plan.bundle
    u, run = _simulate(plan, req, token)
    head = {"model": b.name, "version": b.version}
    flags = assess(getattr(b.model, "envelope_", None), run, u, req.y)
    common = {"confidence": float(run.confidence), "mc_paths": int(run.n_paths), "method": run.method,
              "backend": run.backend,
              "seed": int(req.seed), "start": start_of(plan.operation, req), **flags, **_stream_fields(plan, req, run)}
    steps = int(run.path_steps) if run.method == "mc" else 0
    if plan.operation == "predict":
        out = {**head, "mean": run.mean, "lower": run.lower, "upper": run.upper, "std": run.std, **common,
               "n_samples": int(u.size), "units": dict(b.manifest.get("units") or {})}
        if req.y is not None:
            s = summary(np.asarray(req.y, float), run.mean, run.lower, run.upper)
            out.update(fit=_num(s["fit"]), rmse=_num(s["rmse"]), coverage=_num(s["coverage"]))
        return out, steps
    if plan.operation == "loops":
        phys = physics_of(b)
        kw = dict(fs=b.fs, mass=phys["mass"], input_gain=phys["input_gain"], output=phys["output"])

        def loop(y):
            x, r = restoring_force(u, y, **kw)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
                raise ProblemError(422, "the restoring force is not finite for this record", "u")
            return {"x": x, "force": r, "area": loop_area(x, r)}

        out = {**head, **common, "n_samples": int(u.size), "physics": phys,
               "units": loop_units(b.manifest.get("units"), phys),
               "predicted": loop(run.mean), "lower": loop(run.lower), "upper": loop(run.upper)}
        y = None if req.y is None else np.asarray(req.y, float)
        if y is not None:
            out["measured"] = loop(y)
        if token is not None:
            token.check()
        cyc = cycles(u, b.fs, phys, run.mean, paths=run.paths, cov_band=run.cov_band, y=y,
                     confidence=float(run.confidence))
        out["cycles"] = [{k: (_num(v) if isinstance(v, float) else v) for k, v in c.items()} for c in cyc["cycles"]]
        out["cycle_basis"] = {k: cyc[k] for k in ("basis", "frequency", "n_cycles", "steady_from")}
        return out, steps
    if plan.operation == "novelty":
        nov = novelty_of(b)
        try:
            # a stream's later chunk continues a run begun by the probe's rule: no new start-up to judge
            rule = "measured" if plan.state is not None else start_of(plan.operation, req)
            a = assess_novelty(nov, u, req.y, b.fs, run, start=rule, flags=flags)
        except UnusableProbeContract as exc:  # a malformed contract in the manifest: say so rather than guess
            raise ProblemError(409, f"model {b.name}:{b.version} has an unusable probe contract: {exc}") from None
        except ValueError as exc:
            raise ProblemError(422, f"cannot score this record: {exc}", "y") from None
        probe = {k: a.pop(k) for k in ("probe_match", "probe_reasons", "drive")}
        flagged = a.pop("out_of_range")
        out = {**head, **a, **common, "out_of_range": flagged, **probe}
        return out, steps
    raise ProblemError(422, f"operation must be one of {OPERATIONS}", "operation")
