"""``gpnarx predict``, ``gpnarx loops`` and ``gpnarx novelty`` on record files.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import os
import sys

import numpy as np

from gpnarx.cli.errors import CLIError, UsageError, operation_error
from gpnarx.storage.atomicio import atomic_file


def _common(p):
    p.add_argument("--registry", default=None,
                   help="registry folder or fsspec URL, e.g. s3://bucket/prefix (default: $GPNARX_REGISTRY or the "
                        "default registry, built on first use)")
    p.add_argument("--model", required=True, help="NAME, NAME:VERSION or NAME:ALIAS such as NAME:production (latest "
                                                  "version when omitted)")
    p.add_argument("record", help="record file (.npz, .npy, .csv, .mat) or LMS Test.Lab folder")
    p.add_argument("--mc", type=int, default=None,
                   help="Monte Carlo paths (default: the model's, as the HTTP service and /ui use: see 'gpnarx "
                        "models' / GET /v1/models/NAME default_mc_paths)")
    add_fs_argument(p)
    p.add_argument("--seed", type=int, default=0, help="random seed of the Monte Carlo paths")
    p.add_argument("--method", choices=("mc", "linear"), default=None,
                   help="uncertainty propagation (default: the model's, see 'gpnarx models' / GET /v1/models/NAME "
                        "default_method)")
    p.add_argument("--backend", choices=("numpy", "jax"), default=None,
                   help="array backend of the free run (default: $GPNARX_BACKEND, else numpy); 'jax' runs it as one "
                        "compiled program, on a GPU where JAX has one (pip install 'gpnarx[jax]', docs/accelerator.md)")
    p.add_argument("--blas-threads", type=int, default=None,
                   help="BLAS threads for the free run (default: $GPNARX_BLAS_THREADS or 1; 0 leaves BLAS as it is)")
    p.add_argument("--window", default=None, metavar="START:END",
                   help="use only this time window of the record [s], start inclusive, end exclusive "
                        "(e.g. 30:32 for a steady-state part of a 64 s LMS run)")


def parse_window(spec: str) -> tuple[float, float]:
    """``"START:END"`` in seconds to (start, end); a CLIError naming --window otherwise."""
    parts = spec.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        t0, t1 = float(parts[0]), float(parts[1])
    except ValueError:
        raise UsageError(f"--window must be START:END in seconds, got {spec!r}") from None
    if not (np.isfinite(t0) and np.isfinite(t1) and 0 <= t0 < t1):
        raise UsageError(f"--window needs 0 <= START < END (finite seconds), got {spec!r}")
    return t0, t1


def add_parser(sub):
    p = sub.add_parser("predict", help="free-run prediction with 99%% bounds for a record's input")
    _common(p)
    p.add_argument("--out", default=None, help="write mean/lower/upper/std (and y) to this .npz or .csv")
    p.add_argument("--confidence", type=float, default=0.99, help="band level (default 0.99)")
    p.add_argument("--start", choices=("rest", "measured"), default=None,
                   help="initial state of the free run: 'rest' (default) or 'measured', the record's first ny "
                        "measured outputs (the service's y0; for steady-state records such as sines)")
    p.add_argument("--horizon", type=int, default=None, metavar="K",
                   help="k-step-ahead prediction: restart the run from the record's measured outputs every K "
                        "samples (the record must hold y; K = 1 is the one-step prediction of eqs. 8-9)")
    p.set_defaults(func=run_predict)
    q = sub.add_parser("novelty", help="bolt-loosening novelty score, threshold and verdict for a measured record")
    _common(q)
    q.set_defaults(func=run_novelty)
    lp = sub.add_parser("loops", help="restoring-force loops and per-cycle dissipated energy and secant stiffness "
                                      "with 99%% intervals (the HTTP loops answer)")
    _common(lp)
    lp.add_argument("--confidence", type=float, default=0.99, help="interval level (default 0.99)")
    lp.add_argument("--start", choices=("rest", "measured"), default="rest",
                    help="initial state of the free run: 'rest' (default) or 'measured' (the record's first ny "
                         "measured outputs; for a window of a steady run)")
    lp.add_argument("--arrays", action="store_true",
                    help="also give the loops' x and force arrays (predicted, lower, upper, measured); without it "
                         "each loop holds its area only")
    lp.set_defaults(func=run_loops)


def resolve_registry(registry, name: str | None = None):
    """The registry a command reads, with the meaning ``gpnarx serve`` gives it: ``--registry`` as given;
    else an object-store ``$GPNARX_REGISTRY`` as given (nothing is built there); else the default
    registry folder (``$GPNARX_REGISTRY`` or ~/.cache/gpnarx/registry), where a missing default bundle
    is built first. With ``name`` (the model asked for) only that default (and the one it derives from)
    is built, and none for another name; a build already running (a starting server) is waited for,
    and the wait is said on stderr (``training.defaults.build_lock``)."""
    if registry:
        return registry
    from gpnarx.storage.remote import is_url

    env = os.environ.get("GPNARX_REGISTRY", "")
    if env and is_url(env):
        return env
    from gpnarx.training.defaults import DEFAULT_BUNDLES, DERIVED, default_registry_dir, ensure_default_registry

    if name is None:
        return ensure_default_registry(progress=True)
    if name not in DEFAULT_BUNDLES:
        return default_registry_dir()
    return ensure_default_registry(progress=True, names=[n for n in (DERIVED.get(name), name) if n])


def add_fs_argument(parser) -> None:
    """``--fs HZ`` on ``parser``: the sampling frequency of record files that hold none, read by
    ``read_cli_record`` (the one declaration of predict, loops, novelty, calibrate, predict-many and stream)."""
    parser.add_argument("--fs", type=float, default=None,
                        help="sampling frequency [Hz] of record files that hold none (a CSV without a time column, "
                             "an NPY); checked against a file's own fs otherwise")


def check_fs_option(fs) -> None:
    """``--fs``: None or a finite positive sampling frequency [Hz] (a usage error otherwise)."""
    if fs is not None and not (np.isfinite(fs) and fs > 0):
        raise UsageError(f"--fs must be a finite positive sampling frequency in Hz, got {fs:g}")


def read_cli_record(path, fs=None):
    """The record file ``path``; ``fs`` [Hz]: ``--fs``, needed when the file holds no sampling frequency
    (a CSV without a time column, an NPY; a usage error naming --fs otherwise, as POST /v1/records/parse
    refuses it without its ``fs`` field) and checked against the file's own otherwise."""
    from gpnarx.storage.record_files import read_record
    from gpnarx.storage.record_formats import NoSamplingFrequency

    check_fs_option(fs)
    try:
        rec = read_record(path, fs=fs)
    except NoSamplingFrequency:
        raise UsageError(f"{path}: the file holds no sampling frequency (no time column / fs variable); "
                         f"pass --fs HZ") from None
    if rec.u.ndim != 1 or (rec.y is not None and rec.y.ndim != 1):
        chans = [c.name for c in rec.input_channels() + rec.output_channels()]
        raise CLIError(f"{path}: holds several channels ({', '.join(chans)}); the commands answer single-channel "
                       "records (answers per channel are not built yet)")
    return rec


def load(args, operation: str = "predict"):
    mc_paths(args.mc)
    if args.window:
        parse_window(args.window)
    # the record first: a bad one (or one without fs and no --fs) fails before a default registry is built;
    # predict takes records with gaps (NaN samples, model.gaps), the others refuse them as they read them
    if operation == "predict":
        from gpnarx.model.record import allowing_gaps

        with allowing_gaps():
            rec = read_cli_record(args.record, args.fs)
    else:
        rec = read_cli_record(args.record, args.fs)
    bundle = load_model(args)
    if args.window:
        t0, t1 = parse_window(args.window)
        rec = rec.window(t0, t1)  # a RecordError (ValueError) names the record's span
    rec = check_fs(rec, bundle, args.record)
    return bundle, rec, mc_paths(args.mc, bundle, operation)


def check_fs(rec, bundle, name: str | None = None):
    """``rec`` at the model's fs by the operations' one rule (``operations.check_fs``: within ``FS_RTOL`` the
    record is taken at the model's rate), its refusal a CLIError prefixed by ``name`` (the record as the command
    line gave it, when given)."""
    from dataclasses import replace

    from gpnarx import operations

    try:
        fs = operations.check_fs(rec.fs, bundle)
    except operations.OperationError as exc:
        raise operation_error(exc, name or rec.name) from None
    return rec if fs == rec.fs else replace(rec, fs=fs)


def mc_paths(mc, bundle=None, operation: str = "predict") -> int:
    """``--mc`` by the operations' one rule (``operations.mc_paths_of`` under the bound ``GPNARX_MC_PATHS_MAX``, the
    HTTP service's too), a refusal a usage error naming --mc; without it the bundle's default for ``operation``
    (``operations.default_mc_paths``; before a bundle is loaded, ``--mc`` alone is checked)."""
    from gpnarx import operations

    try:
        limits = operations.Limits(mc_paths_max=operations.mc_paths_max())
    except ValueError as exc:  # GPNARX_MC_PATHS_MAX unusable
        raise UsageError(str(exc)) from None
    default = operations.DEFAULT_MC_PATHS if bundle is None else operations.default_mc_paths(bundle, operation)
    try:
        return operations.mc_paths_of(mc, limits, default)
    except operations.OperationError as exc:
        raise operation_error(exc) from None


def load_model(args):
    """The bundle named by ``--registry`` and ``--model`` (after tuning BLAS for free runs)."""
    from gpnarx.runtime import tune_for_free_run
    from gpnarx.storage.bundle import BundleError
    from gpnarx.storage.registry import parse_model_ref

    if args.blas_threads is not None and args.blas_threads < 0:
        raise UsageError(f"--blas-threads must be >= 0, got {args.blas_threads}")
    tune_for_free_run(args.blas_threads)  # one BLAS thread and no per-step mmaps (see gpnarx/runtime.py)

    try:
        name, version = parse_model_ref(args.model)
    except BundleError as exc:
        raise UsageError(str(exc)) from None
    return open_model(resolve_registry(args.registry, name), name, version)


def open_model(root, name: str, version: str | None):
    """Model ``name`` at ``version`` (a version, an alias such as production, or None: latest) from
    the registry ``root`` (a folder or an fsspec URL): that model's versions are verified, only the
    one asked for is built."""
    from gpnarx.storage.registry import Registry
    from gpnarx.storage.remote import as_local

    local = as_local(root)
    if local is not None and not local.is_dir():
        raise CLIError(f"registry {root} does not exist")
    try:
        return Registry(root, lazy=True).scan(only=name).get(name, version)
    except KeyError as exc:
        msg = exc.args[0]
        if msg.startswith(f"model {name!r} not found"):  # the scan saw only NAME: list the registry's models
            names = model_names(root)
            msg = (f"model {name!r} not found in registry {root}; available: {', '.join(names) or 'none'}"
                   + ("" if names else " (is it still being built? see gpnarx build-defaults)"))
        raise CLIError(msg) from None


def model_names(root) -> list[str]:
    """Names of the models in registry ``root``: folders holding a version with a manifest (a local
    registry, without verifying anything), else a scan."""
    from gpnarx.storage.registry import Registry
    from gpnarx.storage.remote import as_local

    local = as_local(root)
    if local is not None:
        try:
            return sorted(d.name for d in local.iterdir() if d.is_dir() and not d.name.startswith(".")
                          and any((v / "manifest.json").is_file() for v in d.iterdir() if v.is_dir()))
        except OSError:
            return []
    try:
        return Registry(root, lazy=True).scan().names()
    except Exception:  # noqa: BLE001 - a listing for an error message: never hide the original error
        return []


def _progress(enabled, n):
    if not enabled:
        return None, None
    from gpnarx._progress import progress_bar

    bar = progress_bar(total=n, desc="free-run", unit="step", leave=False, mininterval=0.5)
    if bar is None:  # no tqdm (a core install): no bar
        return None, None

    def cb(done, total):
        bar.n = done
        bar.refresh()

    return bar, cb


def _check_out(out: str | None) -> None:
    """Refuse an --out the prediction could not be written to, before the prediction runs."""
    if not out:
        return
    from pathlib import Path

    path = Path(out)
    if path.suffix.lower() not in (".npz", ".csv"):
        raise UsageError(f"--out {out}: name a .npz or .csv file (the suffix picks the format)")
    if path.is_dir():
        raise UsageError(f"--out {out}: is a directory; name a .npz or .csv file")
    if not path.parent.is_dir():
        raise UsageError(f"--out {out}: its folder {path.parent} does not exist")


def run_predict(args):
    _check_out(args.out)
    bundle, rec, mc = load(args)
    args.method = args.method or bundle.default_method("predict")
    bar, cb = _progress(not args.json and sys.stderr.isatty(), rec.n)
    horizon = getattr(args, "horizon", None)
    start = args.start if (args.start is not None or horizon is not None) else "rest"
    try:
        a = operate("predict", bundle, rec, mc=mc, seed=args.seed, confidence=args.confidence, method=args.method,
                    start=start, progress=cb, backend=args.backend, record=args.record, horizon=horizon)
    finally:
        if bar is not None:
            bar.close()
    out = predict_fields(a)
    if args.out:
        _write_prediction(args.out, rec, a.run)
        out["out"] = args.out
    return out


def operate(operation: str, bundle, rec, *, mc: int, seed: int = 0, confidence: float = 0.99,
            method: str | None = None, start: str | None = None, progress=None, backend: str | None = None,
            record: str | None = None, horizon: int | None = None):
    """Operation ``operation`` on a record (an ``operations.Answer``: the answer's body, the free run, the metrics)
    under the process's bounds (``operations.Limits.from_env``), its refusals as CLI errors
    (``cli.errors.operation_error``; ``record``: the record's name in their messages). ``horizon``: k of a
    k-step-ahead prediction (predict; the request's ``horizon``)."""
    from gpnarx import operations

    req = operations.Request(u=rec.u, fs=rec.fs, y=rec.y, mc_paths=mc, seed=seed, confidence=confidence,
                             method=method, backend=backend, start=start, horizon=horizon)
    try:
        plan = operations.plan(operation, req, bundle, operations.Limits.from_env())
        return operations.compute(plan, req, progress=progress)
    except operations.OperationError as exc:
        raise operation_error(exc, record) from None


#: the members of ``gpnarx predict --json``, in order (``operations``' predict answer, ``n`` its n_samples)
PREDICT_FIELDS = ("model", "version", "n", "start", "mc_paths", "method", "backend", "confidence", "seconds",
                  "diverged_paths", "out_of_range", "mean", "lower", "upper", "std")
#: the members of ``gpnarx novelty --json``, in order (a subset of the HTTP novelty answer)
NOVELTY_FIELDS = ("model", "version", "score", "nlpd", "threshold", "verdict", "false_alarm_rate", "out_of_range",
                  "diverged_paths", "start", "score_method", "probe_match", "probe_reasons", "drive")
#: the members of ``gpnarx loops --json`` before its loops, in order
LOOPS_FIELDS = ("model", "version", "n", "start", "mc_paths", "method", "confidence", "diverged_paths",
                "out_of_range", "physics", "units")


def predict_fields(a) -> dict:
    """``gpnarx predict --json`` of the predict operation's answer ``a`` (an ``operations.Answer``): the HTTP
    answer's members in ``PREDICT_FIELDS``, and with a measured y its fit, RMSE, coverage and band width."""
    body = {**a.body, "n": a.body["n_samples"], "seconds": a.run.seconds}
    out = {k: body[k] for k in PREDICT_FIELDS}
    out.update({k: body[k] for k in ("horizon", "gaps") if k in body})  # k-step prediction, a record with gaps
    if a.metrics is not None:
        out.update({k: body[k] for k in ("fit", "rmse", "coverage")}, band_width=a.metrics["band_width"])
    return out


def predict_answer(bundle, rec, *, mc: int, seed: int = 0, confidence: float = 0.99, method: str = "mc",
                   start: str = "rest", progress=None, backend: str | None = None, record: str | None = None) -> dict:
    """The answer of ``gpnarx predict --json`` for one record (``predict_fields``).

    ``bundle``: anything with ``name``, ``version``, ``fs``, ``model`` and ``manifest`` (a loaded Bundle, or
    the light copy ``gpnarx predict-many`` sends to Dask workers).
    """
    return predict_fields(operate("predict", bundle, rec, mc=mc, seed=seed, confidence=confidence, method=method,
                                  start=start, progress=progress, backend=backend, record=record))


def _write_prediction(path, rec, run):
    from pathlib import Path

    path = Path(path)
    cols = {"time": rec.t, "u": rec.u, "mean": run.mean, "lower": run.lower, "upper": run.upper, "std": run.std}
    if rec.y is not None:
        cols["y"] = rec.y
    with atomic_file(path) as f:
        if path.suffix.lower() == ".csv":
            np.savetxt(f, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols), comments="")
        else:
            np.savez(f, fs=rec.fs, **cols)


def run_novelty(args):
    bundle, rec, mc = load(args, "novelty")
    args.method = args.method or bundle.default_method("novelty")
    a = operate("novelty", bundle, rec, mc=mc, seed=args.seed, method=args.method, backend=args.backend,
                record=args.record)
    return {k: a.body[k] for k in NOVELTY_FIELDS}


def run_loops(args):
    """Loops of the predicted mean (and band edges, and the measured record), and per-cycle energy and
    stiffness with intervals across the Monte Carlo paths (``model.cycles``): the HTTP loops answer, each
    loop's x and force arrays only with ``--arrays``."""
    bundle, rec, mc = load(args, "loops")
    args.method = args.method or bundle.default_method("loops")
    bar, cb = _progress(not args.json and sys.stderr.isatty(), rec.n)
    try:
        a = operate("loops", bundle, rec, mc=mc, seed=args.seed, confidence=args.confidence, method=args.method,
                    start=args.start, progress=cb, backend=args.backend, record=args.record)
    finally:
        if bar is not None:
            bar.close()
    body = {**a.body, "n": a.body["n_samples"]}
    out = {k: body[k] for k in LOOPS_FIELDS}
    for key in ("predicted", "lower", "upper", "measured"):
        if key in body:
            loop = body[key]
            out[key] = {"area": loop["area"], **({"x": loop["x"], "force": loop["force"]} if args.arrays else {})}
    out["cycle_basis"] = body["cycle_basis"]
    out["cycles"] = body["cycles"]
    return out
