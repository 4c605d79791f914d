"""``gpnarx stream``: a record, or CSV lines ``u,y`` on stdin as they arrive, predicted chunk by chunk.

Each chunk continues the previous chunk's free run (``FreeRun.state``, the state the HTTP API carries
as a token), so the chunks together are the record predicted whole (docs/api.md, Streams). One JSON
line per chunk on stdout: where it lies in the stream, the band summary, the out-of-range flags, the
cycles completed so far (for a model with physical constants: each cycle once, with its energy and
interval, including cycles that straddle chunks; ``operations.cycle_stream``, the HTTP loops stream's rule),
and, when the chunk has measured outputs and the model a novelty calibration, the chunk's novelty verdict
and the verdict over a rolling window of the last chunks (``operations.novelty_window``, the HTTP novelty
stream's). What a data-acquisition script pipes into.
"""
from __future__ import annotations

import sys

import numpy as np

from gpnarx.cli.cmd_predict import add_fs_argument
from gpnarx.cli.errors import CLIError, UsageError
from gpnarx.model.envelope import assess


def add_parser(sub):
    p = sub.add_parser("stream", help="predict a record or stdin CSV lines 'u,y' chunk by chunk (JSON lines)",
                       description=__doc__)
    p.add_argument("--registry", default=None, help="registry folder or fsspec URL (default: as 'gpnarx predict')")
    p.add_argument("--model", required=True, help="NAME, NAME:VERSION or NAME:ALIAS (latest when omitted)")
    p.add_argument("record", help="record file (.npz, .npy, .csv, .mat, LMS folder), or '-' for CSV lines 'u' or "
                                  "'u,y' on stdin at the model's fs")
    p.add_argument("--chunk", type=float, default=1.0, help="chunk length [s] (default 1)")
    p.add_argument("--method", choices=("mc", "linear"), default=None,
                   help="uncertainty propagation (default: the model's default for predict)")
    p.add_argument("--mc", type=int, default=None,
                   help="Monte Carlo paths (default: the model's, as 'gpnarx predict' and the HTTP service)")
    add_fs_argument(p)
    p.add_argument("--seed", type=int, default=0, help="random seed of the Monte Carlo paths")
    p.add_argument("--window", type=int, default=8,
                   help="the rolling novelty window, in chunks: it scores the last WINDOW x --chunk seconds "
                        "(default 8)")
    p.add_argument("--blas-threads", type=int, default=None, help="BLAS threads (default as 'gpnarx predict')")
    p.set_defaults(func=run_stream, backend=None)
    return p


def _stdin_chunks(n: int):
    """Chunks of ``n`` samples (u, y or None) from CSV lines on stdin, each yielded as soon as it is full;
    the last may be shorter. A header line (non-numeric) is skipped; a malformed line is an error naming it."""
    us, ys, width = [], [], None
    for k, line in enumerate(sys.stdin, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            if k == 1:
                continue  # a header
            raise CLIError(f"stdin line {k}: expected 'u' or 'u,y' numbers, got {line[:60]!r}") from None
        if width is None:
            width = len(vals)
        if len(vals) != width or width not in (1, 2) or not all(np.isfinite(vals)):
            raise CLIError(f"stdin line {k}: expected {width if width in (1, 2) else '1 or 2'} finite numbers "
                           f"('u' or 'u,y'), got {line[:60]!r}")
        us.append(vals[0])
        if width == 2:
            ys.append(vals[1])
        if len(us) == n:
            yield np.array(us), (np.array(ys) if ys else None), False
            us, ys = [], []
    if us:
        yield np.array(us), (np.array(ys) if ys else None), True


def _record_chunks(rec, n: int):
    for c in range(0, rec.n, n):
        yield rec.u[c:c + n], (None if rec.y is None else rec.y[c:c + n]), c + n >= rec.n


def run_stream(args):
    from gpnarx.cli.cmd_predict import check_fs, load_model, mc_paths, read_cli_record
    from gpnarx.cli.errors import operation_error
    from gpnarx.model.metrics import summary
    from gpnarx.model.novelty import assess_novelty, novelty_start
    from gpnarx.operations import OperationError, physics_of
    from gpnarx.operations import check_fs as check_rate
    from gpnarx.operations.cycle_stream import STREAM_COV_WINDOW
    from gpnarx.operations.cycle_stream import advance as stream_cycles
    from gpnarx.operations.novelty_window import RollingWindow
    from gpnarx.storage.jsonsafe import dumps_json

    if not args.chunk > 0:
        raise UsageError(f"--chunk must be a positive number of seconds, got {args.chunk}")
    if args.window < 1:
        raise UsageError(f"--window must be at least 1 chunk, got {args.window}")
    mc_paths(args.mc)
    # a record file first: one without fs and no --fs fails before a default registry is built
    rec = None if args.record == "-" else read_cli_record(args.record, args.fs)
    bundle = load_model(args)
    model, fs = bundle.model, bundle.fs
    method = args.method or bundle.default_method("predict")
    mc = mc_paths(args.mc, bundle)
    n = max(int(round(args.chunk * fs)), model.ny + 1)
    if args.record == "-":
        try:  # stdin lines are taken at the model's fs: a --fs given must be it (the operations' rule)
            if args.fs is not None:
                check_rate(args.fs, bundle)
        except OperationError as exc:
            raise operation_error(exc, "--fs") from None
        chunks = _stdin_chunks(n)
    else:
        rec = check_fs(rec, bundle, args.record)
        chunks = _record_chunks(rec, n)
    nov = bundle.manifest.get("novelty")
    window = RollingWindow(int(args.window) * n)  # the last chunks' samples, for the rolling score
    try:
        phys = physics_of(bundle)  # completed cycles need the restoring force's constants
    except OperationError:
        phys = None
    extra = {} if phys is None else ({"keep_paths": True} if method == "mc" else {"cov_window": STREAM_COV_WINDOW})
    state, t, loops = None, 0, None
    for k, (u, y, last) in enumerate(chunks):
        y0 = None
        if state is None and y is not None and nov and u.size > model.ny:
            y0 = novelty_start(y, model.ny)  # a monitor's stream starts as its calibration did
        run = model.simulate(u, n_paths=mc, seed=args.seed, method=method, y0=y0, state=state, open_end=not last,
                             **extra)
        state = run.state
        flags = assess(getattr(model, "envelope_", None), run, u, y)
        line = {"model": bundle.name, "version": bundle.version, "chunk": k, "start_s": t / fs,
                "end_s": (t + u.size) / fs, "n_samples": int(u.size), "method": run.method,
                "mean_rms": float(np.sqrt(np.mean(run.mean ** 2))),
                "band_half_width_mean": float(np.mean(run.upper - run.lower) / 2.0), **flags}
        if phys is not None:
            done, loops = stream_cycles(loops, u, run.mean, fs=fs, physics=phys, y=y, paths=run.paths,
                                        cov_band=run.cov_band, confidence=float(run.confidence))
            line["cycles"] = done
        if y is not None:
            s = summary(y, run.mean, run.lower, run.upper)
            line.update(fit=s["fit"], coverage=s["coverage"])
            if nov:
                a = assess_novelty(nov, u, y, fs, run, start="measured", flags=flags)
                line["novelty"] = {key: a[key] for key in ("score", "threshold", "verdict")}
                line["novelty_window"] = window.add(u, y, run.mean, run.std, flags).assess(nov, fs)
        sys.stdout.write(dumps_json(line).decode() + "\n")
        sys.stdout.flush()
        t += u.size
    return None
