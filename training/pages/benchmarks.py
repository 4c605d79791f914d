"""docs/benchmarks.md from the stored RESULT lines of the bench scripts (docs/runs/bench/*.txt and the GPU run in
docs/runs/accelerator/bench_gpu.txt): every figure on the page is a field of a stored line, so the page cannot
drift from its runs (tests/test_results_pages.py re-renders it).

A run file holds RESULT lines as a bench script prints them; a ``# run: TEXT`` line says what the file's
runs are (machine, load, settings) and a ``# `` line right before a RESULT line names its command.

Usage (from the repository root): ``python -m gpnarx.training.pages benchmarks docs/runs docs/benchmarks.md``; to
publish a new run, put its RESULT lines (with their ``#`` command line) in a file under docs/runs/bench/ and
re-render.
"""
from __future__ import annotations

from pathlib import Path

from gpnarx.training.pages.markdown import row, rule, stored_run

# the stored run files, in page order: (path under docs/runs, heading, command of lines that name none)
SOURCES = (("bench/quick.txt", "Quick mode (the smoke test's settings)", None),
           ("bench/full.txt", "Full-size runs", None),
           ("bench/first_start.txt", "First start: the default build on an empty registry", None),
           ("bench/memory_pipeline.txt", "Peak memory of whole gpnarx processes: train, predict, Monte Carlo predict "
            "and build-defaults (bench_memory.py --pipeline)", None),
           ("bench/mc_speed.txt", "Monte Carlo with the checked local model on 2 cores (bench_mc_speed.py)", None),
           ("bench/pinned2.txt", "Two cores of a quiet machine (bench_realtime.py, bench_mc_speed.py --whole)", None),
           ("bench/exact_2core.txt", "The exact bert-real on the shared 2-core machine (bench_realtime.py, "
            "bench_mc_speed.py --whole --seconds 2)", None),
           ("bench/exact_2core_quiet.txt", "The exact bert-real on the quiet 2-core machine (bench_realtime.py, "
            "bench_mc_speed.py --whole --seconds 2 at 1 and 2 BLAS threads)", None),
           ("bench/exact_2core_quiet_ny16.txt", "The exact bert-real at ny = 16, nu = 20 on the quiet 2-core machine "
            "(bench_realtime.py, bench_mc_speed.py --whole --seconds 2 at 1 and 2 BLAS threads)", None),
           ("bench/exact_2core_quiet_startup.txt", "The exact bert-real on the quiet 2-core machine, lighter start-up "
            "(bench_realtime.py with the free run's own time, bench_mc_speed.py --whole --seconds 2)", None),
           ("bench/sparse_vs_exact_2core.txt", "The exact and the sparse bert-real side by side on the 2-core "
            "machine (bench_realtime.py, bench_mc_speed.py --whole --seconds 2; posterior= and heldout_fit_min= "
            "say what each keeps of the fidelity)", None),
           ("bench/kstep.txt", "k-step-ahead prediction at k = 64 against the free run on the same record and model "
            "(bench_kstep.py)", None),
           ("bench/local_check.txt", "Does the Monte Carlo local model's check bound the error at every path? "
            "(bench_local_check.py)", None),
           ("bench/wire.txt", "One 64 s predict answer as JSON, gzip JSON and NPZ (bench_wire.py)", None),
           ("bench/stream.txt", "A real 64 s record in 1 s chunks against the record whole (bench_stream.py)", None),
           ("bench/streams.txt", "Streams per replica: sensor streams one 2-core replica of the exact bert-real "
            "follows in real time (bench_streams.py)", None),
           ("bench/exact_2core_compiled.txt", "The exact bert-real with the compiled pass 1 against the code "
            "before it, on the shared 2-core machine (bench_realtime.py --baseline-ref, bench_mc_speed.py --whole "
            "--seconds 2)", None),
           ("bench/exact_2core_quiet_compiled.txt", "The exact bert-real, whole gpnarx predict process, on the quiet "
            "2-core machine with and without the compiled passes, against the code before them (bench_realtime.py "
            "--baseline-ref)", None),
           ("bench/streams_replicas.txt", "Streams with two replicas behind one address, and the stand-in "
            "monitor's novelty stream (bench_streams.py --replicas, --operation novelty)", None),
           ("bench/estimator_blas.txt", "The Python API's free run with and without its own BLAS limit "
            "(bench_estimator_blas.py)", None),
           ("bench/update.txt", "An update from one new record against a retrain: gpnarx update bert-real with one "
            "16 s record against gpnarx train bert-real, same run (bench_update.py)", None),
           ("accelerator/bench_gpu.txt", "GPU run, H100 (results: [results-accelerator.md](results-accelerator.md))",
            "bench/bench_gpu.py (commands: docs/runs/accelerator/run.json)"),
           ("accelerator/h200/bench_gpu.txt", "GPU run, H200",
            "bench/bench_gpu.py (commands: docs/runs/accelerator/h200/run.json)"),
           ("accelerator/h200/bench_gpu_steps.txt", "GPU time per step by variant, H200",
            "bench/bench_gpu_steps.py (commands: docs/runs/accelerator/h200/run.json)"))
# runs that are a product figure only, with no same-run baseline (so no ratio=): their lines are listed as they are
FIGURES = (("bench/first_start_real.txt", "First start with the lab records (no same-run baseline)", None),)
# fields shown in their own columns; the rest of each line is listed after the table
COLUMNS = ("ratio", "baseline", "baseline_what", "user_ratio", "user_baseline")

METHOD = """\
# Benchmarks

Rendered by `python -m gpnarx.training.pages benchmarks docs/runs docs/benchmarks.md` from the stored RESULT lines
in `docs/runs/bench/` (and the GPU run in `docs/runs/accelerator/bench_gpu.txt`); do not edit by hand:
`tests/test_results_pages.py` re-renders the page
and fails when it differs. The history of earlier runs (before/after tables, commit hashes, load) is in
[CHANGELOG.md](../CHANGELOG.md#history-of-published-figures).

## Method

Regenerate a figure with `python bench/<script>.py` from the repository root (each script's options:
`--help`). Each script prints one line that starts with `RESULT ` followed by `key=value` pairs: the
product's figure, the baseline's (`baseline=`, said in words by `baseline_what=`) and `ratio=`. `--quick` is
what the test suite runs (`tests/test_bench_smoke.py` checks that every line has `ratio=`, `baseline=` and
`baseline_what=`). `--threads N` limits BLAS to N threads for both sides.

**`ratio=` compares equal work**: the same model size (training rows or inducing points), precision,
BLAS thread count and process tuning on both sides; repetitions interleaved (A, B, A, B, ...) so that load
from other processes hits both; the median of the per-repetition ratios. Where scikit-learn has no
equivalent (sparse GP, linearised propagation, service overhead), the baseline is the product's own previous
or alternative code path or a plain numpy/scipy implementation of the same equations, and `baseline_what=`
says which. A comparison with what a user would otherwise run (scikit-learn exact at the protocol's size,
library defaults) is not equal work: it is reported in separate fields, `user_ratio...=`, labelled by
`user_baseline=`. The in-process benches whose baseline evaluates eqs. 8-9 at every path (`bench_freerun`,
`bench_modes`, `bench_scaling`, `bench_memory`, `bench_bert_scale`) pass `local=False` to `simulate_mc` /
`GPNARX.simulate`, so their `ratio=` compares the same algorithm; `bench_mc_speed.py` compares the default
(the checked local model) with the previous code of the same algorithm, and `bench_predict_e2e.py` times the
`gpnarx predict` process against a process evaluating every path, so its ratio includes that change of algorithm.
A baseline that is earlier product code comes from the git history (`bench/baseline.py` imports a commit's
`model/` beside the product), not from a copy in the tree; in a shallow clone that bench skips its baseline and
says why (`baseline_skipped=`).

`bench/` holds the benchmarks only. Tools that measure something else live in `tools/`: `tools/fault_probes.py`
(the fault probes against `gpnarx serve`; stored run `docs/runs/faults/probes.txt`), `tools/install_sizes.py`
(the install tiers' sizes, rendered into [deploy.md](deploy.md)) and `tools/answers_snapshot.py` (digests of the
product's answers, to check that a refactor changes none).

"""


# what each script compares: (script, product, equal-work baseline of ratio=)
METHOD_ROWS = (
    ('`bench_freerun.py`',
     'exact Monte Carlo free run (`simulate_mc`)',
     'scikit-learn `GaussianProcessRegressor.predict(return_std=True)` loop, same rows, kernel, hyperparameters '
     'and seed'),
    ('`bench_modes.py`',
     'exact, sparse and linearised free runs',
     'exact: scikit-learn at the same size; sparse: `_common.NumpySparse`, numpy/scipy on the same posterior; '
     "linearised: the product's own Monte Carlo on the same model"),
    ('`bench_fit.py`',
     'ML-II',
     "one NLML + gradient evaluation against scikit-learn's `log_marginal_likelihood(eval_gradient=True)` at the "
     'same size; `fit_ratio_plain=`: whole fits with the same L-BFGS-B settings and start'),
    ('`bench_scaling.py`',
     'log-log slopes of fit, step, paths and record length',
     'scikit-learn `predict` per step at the largest size, same block'),
    ('`bench_memory.py`',
     'peak memory of a Monte Carlo free run; `--pipeline`: peak RSS of whole `gpnarx train`, `predict`, '
     '`predict --method mc` and `build-defaults` processes',
     'scikit-learn loop, same size and paths; `--pipeline`: the same `gpnarx train` with the held-out noise '
     'calibration in one call over every row (the code before its row blocks), same run'),
    ('`bench_bert_scale.py`',
     "the BERT stand-in run at the paper's scale, sparse",
     '`NumpySparse` on the same posterior, same first steps'),
    ('`bench_predict_e2e.py`',
     '`gpnarx predict` as a process (tuned: one BLAS thread, malloc threshold)',
     'a process doing the same job on the same bundle with the same tuning (`NumpySparse`)'),
    ('`bench_estimator_blas.py`',
     '`GPNARX.simulate` through the Python API, BLAS limited by the estimator around its free run',
     'the same call, same process, model, record, paths and seed with `GPNARX_BLAS_THREADS=0` (BLAS at the '
     "library's default threads), interleaved"),
    ('`bench_gpu.py`',
     'Monte Carlo free run on the JAX backend',
     'the numpy backend on the same bundle, paths and seed, on the CPU cores beside it'),
    ('`bench_gpu_steps.py`',
     'time per step of the JAX Monte Carlo block, variant by variant, and `GPNARX.simulate` itself',
     'the previous joint product K [F^T | w] of the same arrays, steps and paths'),
    ('`bench_linear_band.py`',
     'linearised 99 % band',
     "the product's Monte Carlo band on the same model; ratio of mean widths (accuracy)"),
    ('`bench_sparse_accuracy.py`',
     'sparse, all rows, linearised',
     "the product's exact posterior on fewer rows, same hyperparameters; ratio of the lowest coverages (accuracy)"),
    ('`bench_sparse_variance.py`',
     'factored sparse variance \\|G k\\|^2',
     'single-matrix k^T A k on the same posterior; ratio of times (lower is better)'),
    ('`bench_service.py`',
     'predict over loopback HTTP',
     'the same prediction in-process, same tuning, alternating'),
    ('`bench_wire.py`',
     'a predict call with an NPZ body and answer',
     'the same call with JSON (and gzip) bodies, interleaved; ratio = JSON / NPZ wire time'),
    ('`bench_load.py`',
     'concurrent clients against `gpnarx serve`',
     'one sequential client, same calls, same server, alternating'),
    ('`bench_bombs.py`',
     'decompression bombs against `gpnarx serve` (a forged stream token, an HDF5 upload of one 512 MiB gzip chunk): '
     'peak RSS growth and the slowest `/health/live` while each is refused',
     "the same routes with legitimate requests (this model's own token, a 10-sample HDF5 upload); ratio = the "
     "bombs' largest RSS growth / the legitimate requests' (about 1: a bomb costs what a legitimate request costs)"),
    ('`bench_mc_speed.py`',
     'Monte Carlo free run with the checked local model',
     'the previous product code of the same algorithm (`simulate_mc` of git commit 9ee9349f2ece, imported from the '
     'history by `bench/baseline.py`), same posterior, paths and seed, interleaved; `ratio_exact=`: '
     '`freerun_reference.simulate_mc_reference` (eqs. 8-9 at every path), timed once'),
    ('`bench_local_check.py`',
     'the Monte Carlo local model against eqs. 8-9 at every path, every step its check passed (errors in '
     'tolerance units; `exceed_steps=`: the check\'s misses)',
     'the largest error the check itself sees, at the 6 farthest paths of the same steps; ratio = largest error at '
     'any path / that (1: the farthest paths held the worst error)'),
    ('`bench_realtime.py`',
     'the whole `gpnarx predict --method linear` process: real-time factor',
     'the same process with the reference linearised loop, alternating; with `--baseline-ref REF`, the same '
     'process run by the whole package of git commit REF'),
    ('`bench_kstep.py`',
     'the k-step-ahead prediction at k = 64 (`predict` with `horizon`: restarts from the measured outputs every 64 '
     'samples; linearised, the segments as one batch), and by Monte Carlo (`mc_ratio`)',
     'the free run from the measured start on the same record, model and process; ratio = k-step / free-run wall '
     'time (lower is faster)'),
    ('`bench_stream.py`',
     'a record predicted in chunks with state tokens',
     'the same record whole'),
    ('`bench_streams.py`',
     'streams per replica: the most clients one `gpnarx serve` follows in real time, each streaming a record in '
     '1 s chunks with state tokens (p99 under the chunk time, no 503, error or lag)',
     'one stream alone: the bound floor(workers x chunk / its median chunk latency) if chunks shared the workers '
     'perfectly (`--replicas R`: R replicas behind one round-robin address, R x workers)'),
    ('`bench_update.py`',
     '`gpnarx update` with one new record (the rank update of the exact posterior and the noise, band and novelty '
     'recalibrations of its config)',
     '`gpnarx train` of the same model in the same run; ratio = update / train wall time (lower is better; target '
     '0.1)'),
    ('`bench_first_start.py`',
     '`gpnarx serve` on an empty registry',
     'the previous start path (build, then serve)'),
)


def _cell(v) -> str:
    """A field as the table prints it: a number as it is, a label in code font, '-' where the line has none."""
    if v is None:
        return "-"
    try:
        float(v)
        return v
    except ValueError:
        return f"`{v}`"


def _heading(path: Path, runs: Path, heading: str, about: str | None) -> list[str]:
    rel = path.relative_to(runs.parent.parent).as_posix()
    return [f"## {heading}\n", f"Stored run: `{rel}`." + (f" {about}" if about else "") + "\n"]


def section(path: Path, runs: Path, heading: str, default_command: str | None = None) -> str:
    about, rows = stored_run(path.read_text())
    out = _heading(path, runs, heading, about)
    out.append(row(["command"] + [f"`{c}=`" for c in COLUMNS]))
    out.append(rule(1 + len(COLUMNS)))
    for command, kv in rows:
        out.append(row([f"`{command or default_command}`"] + [_cell(kv.get(c)) for c in COLUMNS]))
    out.append("\nThe other fields of each line:\n")
    for command, kv in rows:
        rest = " ".join(f"{k}={v}" for k, v in kv.items() if k not in COLUMNS)
        out.append(f"- `{command or default_command}`: `{rest}`")
    return "\n".join(out) + "\n"


def render(runs) -> str:
    """The page from the stored runs under ``runs`` (the repository's ``docs/runs``)."""
    runs = Path(runs).resolve()
    table = "\n".join([row(["script", "product", "`ratio=`: equal-work baseline"]), rule(3)]
                      + [row(r) for r in METHOD_ROWS])
    parts = [METHOD + table + "\n"]
    for rel, heading, command in SOURCES:
        if (runs / rel).is_file():
            parts.append(section(runs / rel, runs, heading, command))
    for rel, heading, command in FIGURES:
        if (runs / rel).is_file():
            parts.append(figures_section(runs / rel, runs, heading, command))
    return "\n".join(parts)


def figures_section(path: Path, runs: Path, heading: str, default_command: str | None = None) -> str:
    """A run of ``FIGURES``: its description and each RESULT line's fields, no baseline columns."""
    about, rows = stored_run(path.read_text())
    out = _heading(path, runs, heading, about)
    for command, kv in rows:
        out.append(f"- `{command or default_command}`: `{' '.join(f'{k}={v}' for k, v in kv.items())}`")
    return "\n".join(out) + "\n"
