"""``gpnarx predict-many RECORD... --registry R --model NAME[:VERSION] --out DIR [--scheduler ADDRESS]``.

Bulk free-run prediction: every record gets the answer ``gpnarx predict --json`` gives for it (same
fields, same numbers for the same ``--seed``), written to ``DIR/<record>.json``, and ``DIR/index.json``
lists every record with its status (``ok`` or ``failed`` with the error), file and headline figures.
A record that cannot be read or predicted is reported there and does not stop the others; the exit
code is 0 when every record succeeded and 1 otherwise (2 for a usage error, as everywhere).

The records are read here. Locally they run one after the other (``--jobs 1``, the default) or on
local cores with joblib; with ``--scheduler`` each record's arrays are sent to a Dask worker along
with the model (sent once to every worker), so the workers need neither the record files nor the
registry. ``--out`` is a folder, or an fsspec URL (``s3://bucket/prefix``, ``file://...``) when fsspec
and the protocol's package are installed.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import importlib.util
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from gpnarx.cli.cmd_predict import add_fs_argument
from gpnarx.cli.errors import CLIError, UsageError
from gpnarx.storage.atomicio import write_atomic

INDEX = "index.json"


def add_parser(sub):
    p = sub.add_parser("predict-many", help="free-run prediction of many records to a results folder "
                                            "(one JSON per record plus index.json), locally or on a Dask cluster")
    p.add_argument("records", nargs="+", metavar="RECORD",
                   help="record files (.npz, .npy, .csv, .mat) or LMS Test.Lab folders")
    p.add_argument("--registry", default=None,
                   help="registry folder or URL (default: $GPNARX_REGISTRY or the default registry)")
    p.add_argument("--model", required=True, help="NAME or NAME:VERSION (latest version when omitted)")
    p.add_argument("--out", required=True, help="results folder (created), or an fsspec URL")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask scheduler, e.g. tcp://host:8786 (needs the 'dask' extra); default: "
                        "this machine")
    p.add_argument("--jobs", type=int, default=1, help="local parallel jobs without --scheduler (joblib; -1 = all "
                                                       "cores; default 1: one record after the other)")
    p.add_argument("--mc", type=int, default=None,
                   help="Monte Carlo paths (default: the model's, as 'gpnarx predict' and the HTTP service)")
    add_fs_argument(p)
    p.add_argument("--seed", type=int, default=0, help="random seed of the Monte Carlo paths (the same for every "
                                                       "record, as 'gpnarx predict --seed')")
    p.add_argument("--method", choices=("mc", "linear"), default=None,
                   help="uncertainty propagation (default: the model's default_method)")
    p.add_argument("--confidence", type=float, default=0.99, help="band level (default 0.99)")
    p.add_argument("--start", choices=("rest", "measured"), default="rest",
                   help="initial state of every free run: 'rest' (default) or 'measured' (each record's first ny "
                        "measured outputs)")
    p.add_argument("--backend", choices=("numpy", "jax"), default=None,
                   help="array backend of every free run (default: $GPNARX_BACKEND, else numpy; docs/accelerator.md)")
    p.add_argument("--blas-threads", type=int, default=None,
                   help="BLAS threads per free run (default: $GPNARX_BLAS_THREADS or 1; 0 leaves BLAS as it is)")
    p.set_defaults(func=run)


@dataclass(frozen=True)
class ModelCopy:
    """What a free run and its answer need from a bundle; sent to the workers instead of a path."""

    name: str
    version: str
    model: object
    manifest: dict
    fs: float  # [Hz]


def predict_record(bundle: ModelCopy, rec, options: dict) -> dict:
    """One record's ``gpnarx predict --json`` answer (arrays kept as numpy): the task a worker runs."""
    from threadpoolctl import threadpool_limits

    from gpnarx.cli.cmd_predict import predict_answer

    blas = options.get("blas_threads", 1)
    opts = {k: v for k, v in options.items() if k != "blas_threads"}
    if blas:
        with threadpool_limits(limits=int(blas), user_api="blas"):
            return predict_answer(bundle, rec, **opts)
    return predict_answer(bundle, rec, **opts)


def _file_names(paths: list[str]) -> list[str]:
    """One result file name per record: its file or folder stem, made unique (``-2``, ``-3`` ...)."""
    names, used = [], {Path(INDEX).stem}
    for p in paths:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(p.rstrip("/\\")).stem or "record").strip("._") or "record"
        name, k = stem, 2
        while name in used:
            name, k = f"{stem}-{k}", k + 1
        used.add(name)
        names.append(f"{name}.json")
    return names


class _Results:
    """Writes result files into a folder (atomically) or under an fsspec URL."""

    def __init__(self, out: str):
        self.out = out
        self.url = "://" in out and not out.startswith("file://")
        if self.url:
            if importlib.util.find_spec("fsspec") is None:
                raise CLIError(f"--out {out}: an URL needs fsspec (and the protocol's package, e.g. s3fs)")
            import fsspec

            try:
                self.fs, self.root = fsspec.core.url_to_fs(out)
            except (ImportError, ValueError) as exc:
                raise CLIError(f"--out {out}: {exc}") from None
            self.root = self.root.rstrip("/")
            self.fs.makedirs(self.root, exist_ok=True)
        else:
            self.dir = Path(out[len("file://"):] if out.startswith("file://") else out).expanduser()
            if self.dir.exists() and not self.dir.is_dir():
                raise CLIError(f"--out {out} exists and is not a folder")
            try:
                self.dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CLIError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") from None

    def write(self, name: str, text: str) -> str:
        if self.url:
            path = f"{self.root}/{name}"
            with self.fs.open(path, "w") as f:
                f.write(text)
            return f"{self.out.rstrip('/')}/{name}"
        target = self.dir / name
        write_atomic(target, text)
        return str(target)


def _first_line(exc: BaseException) -> str:
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"missing key {exc}" if isinstance(exc, KeyError) else msg


def run(args):
    from gpnarx.cli.cmd_predict import check_fs_option, mc_paths
    from gpnarx.training.distributed import TaskRunner

    if args.scheduler is not None and not args.scheduler.strip():
        raise UsageError("--scheduler must be a Dask scheduler address such as tcp://host:8786")
    if args.scheduler and importlib.util.find_spec("distributed") is None:
        raise CLIError("--scheduler needs dask.distributed: pip install 'gpnarx[dask]'")
    if args.jobs == 0 or args.jobs < -1:
        raise UsageError(f"--jobs must be a positive number of jobs or -1 (all cores), got {args.jobs}")
    if not 0 < args.confidence < 1:
        raise UsageError(f"--confidence must be between 0 and 1 (exclusive), got {args.confidence}")
    mc_paths(args.mc)  # checked now; None: the model's default, once it is loaded
    check_fs_option(args.fs)
    # the cluster first: an unreachable scheduler fails before any folder is made or model loaded
    with TaskRunner(args.scheduler, jobs=1 if args.scheduler else args.jobs) as runner:
        return _run(args, runner)


def _run(args, runner) -> dict:
    from gpnarx.cli.cmd_predict import check_fs, load_model, mc_paths, read_cli_record
    from gpnarx.runtime import blas_threads_from_env
    from gpnarx.storage.jsonsafe import to_json_safe
    from gpnarx.training.distributed import Failed

    out = _Results(args.out)
    bundle = load_model(args)
    args.method = args.method or bundle.default_method("predict")
    mc = mc_paths(args.mc, bundle)
    # load_model has checked GPNARX_BLAS_THREADS; the same limit applies to every free run, on a worker too
    blas = args.blas_threads if args.blas_threads is not None else blas_threads_from_env()
    options = {"mc": mc, "seed": args.seed, "confidence": args.confidence, "method": args.method,
               "start": args.start, "blas_threads": blas, "backend": args.backend}
    files = _file_names(args.records)
    entries = [{"record": str(p), "file": None, "status": "failed", "error": None} for p in args.records]
    bar = None
    if not args.json:
        from gpnarx._progress import progress_bar

        bar = progress_bar(total=len(args.records), desc="predict-many", unit="record")
    t0 = time.perf_counter()
    shared = runner.share(ModelCopy(bundle.name, bundle.version, bundle.model, bundle.manifest, bundle.fs))

    def calls():
        for path in args.records:
            try:  # read here: a worker gets the arrays, never the path
                rec = check_fs(read_cli_record(path, args.fs), bundle, str(path))
            except (CLIError, ValueError, OSError, KeyError, LookupError) as exc:
                yield Failed(exc)
                continue
            yield shared, runner.send(rec), options

    for i, res, exc in runner.imap(predict_record, calls()):
        e = entries[i]
        if exc is None:
            try:
                answer = to_json_safe(res)
                e["file"] = Path(out.write(files[i], json.dumps(answer, allow_nan=False))).name
            except (OSError, ValueError) as werr:
                exc = werr
            else:
                e.update(status="ok", **{k: answer.get(k) for k in ("n", "fit", "rmse", "coverage",
                                                                    "diverged_paths", "out_of_range", "seconds")})
        if exc is not None:
            e["error"] = _first_line(exc)
            # read errors already name the record
            msg = "gpnarx predict-many: " + (e["error"] if e["record"] in e["error"]
                                             else f"{e['record']}: {e['error']}")
            if bar is not None:
                bar.write(msg, file=sys.stderr)
            else:
                print(msg, file=sys.stderr)
        if bar is not None:
            bar.update(1)
    where = runner.where
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    ok = sum(e["status"] == "ok" for e in entries)
    index = {"model": bundle.name, "version": bundle.version, "records": entries, "n_records": len(entries),
             "ok": ok, "failed": len(entries) - ok, "mc_paths": mc, "seed": args.seed, "method": args.method,
             "start": args.start, "confidence": args.confidence, "where": where, "wall_seconds": wall}
    index_path = out.write(INDEX, json.dumps(to_json_safe(index), indent=1, allow_nan=False))
    if ok < len(entries):
        args.exit_code = 1
    return {"model": bundle.name, "version": bundle.version, "out": args.out, "index": index_path,
            "records": len(entries), "ok": ok, "failed": len(entries) - ok, "where": where, "wall_seconds": wall}
