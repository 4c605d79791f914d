"""``gpnarx reproduce bouc-wen|bert-standin|bert-real|bert-real-paper [--quick] [--out DIR]``, and
``gpnarx reproduce STUDY -- ARGS``: a study of the repository's ``studies/`` folder (a checkout's, not the
wheel's) with its own arguments.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import sys

SYSTEMS = ("bouc-wen", "bert-standin", "bert-real", "bert-real-paper")


def add_parser(sub):
    from gpnarx.training.checkout import STUDIES  # a dict of names only: no numerics imported

    p = sub.add_parser("reproduce", help="run the paper's protocol end to end (lag surface, train, verify, "
                                         "validate, baselines, report), or a study of a repository checkout")
    p.add_argument("system", choices=SYSTEMS + tuple(STUDIES),
                   help="a protocol, or a study of the repository's studies/ folder (needs a checkout; give its "
                        "own arguments after --, e.g. gpnarx reproduce cycle-study -- --registry R --help)")
    p.add_argument("study_args", nargs="*", metavar="-- ARGS", help="a study's own arguments (after --)")
    p.add_argument("--out", default=None, help="output folder (default: runs/reproduce-SYSTEM)")
    p.add_argument("--quick", action="store_true", help="same code path on a tiny grid, short records, few paths")
    p.add_argument("--jobs", type=int, default=-1, help="parallel jobs for the lag surface")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address for the lag surface")
    p.add_argument("--mc", type=int, default=None, help="Monte Carlo paths (default: 1024 Bouc-Wen, 4096 BERT)")
    p.add_argument("--docs", default=None, metavar="FILE",
                   help="also write the results page there (docs/results-SYSTEM.md); the run folder always "
                        "holds it as results-SYSTEM.md")
    p.add_argument("--table-mc", type=int, default=None, metavar="N",
                   help="bert-real: Monte Carlo paths of the every-record table (default: --mc; 0: linearised only)")
    p.add_argument("--table-only", action="store_true",
                   help="bert-real: score the run folder --out's own bundle on every real record again with "
                        "--table-mc paths and re-render its page (and --docs), training nothing")
    p.add_argument("--table-mc-class", default=None, metavar="CLASS",
                   help="with --table-only: Monte Carlo on the records of one class only (e.g. noise), the others "
                        "linearised")
    p.add_argument("--bundle", default=None, metavar="DIR",
                   help="with --table-only: score this bundle (trained from the shipped config) instead of the run's")
    p.add_argument("--from-run", action="store_true",
                   help="only re-render the results page (--docs) from the run folder --out, computing nothing")
    p.set_defaults(func=run)


def run(args):
    if args.system not in SYSTEMS:
        return run_study(args)
    if args.study_args:
        from gpnarx.cli.errors import UsageError

        raise UsageError(f"gpnarx reproduce {args.system} takes no arguments after its options: "
                         f"{' '.join(args.study_args)}")
    # start-up: imported when the command runs (see gpnarx.cli)
    from gpnarx.training.reproduce import reproduce

    out = args.out or f"runs/reproduce-{args.system}{'-quick' if args.quick else ''}"
    if args.table_only:
        from pathlib import Path

        from gpnarx.cli.errors import CLIError, UsageError
        from gpnarx.training.reproduce import rescore_table

        if args.system != "bert-real" or args.table_mc is None:
            raise UsageError("--table-only re-scores a bert-real run's every-record table: give bert-real and "
                           "--table-mc N")
        if not (Path(out) / "summary.json").is_file():
            raise CLIError(f"--table-only: no summary.json in {out} (run gpnarx reproduce bert-real --out {out})")
        log = None if args.json else (lambda m: print(m, file=sys.stderr, flush=True))
        s = rescore_table(out, args.table_mc, jobs=args.jobs, docs_page=args.docs, log=log,
                          mc_class=args.table_mc_class, bundle=args.bundle)
        return {"system": args.system, "out": out, "docs": args.docs, "real_table_checks": s["real_table"]["checks"]}
    if args.from_run:
        from gpnarx.cli.errors import CLIError, UsageError
        from gpnarx.training.reproduce import render_from_run

        if not args.docs:
            raise UsageError("--from-run re-renders the results page from the run folder --out: give --docs FILE")
        import json
        from pathlib import Path

        summary = Path(out) / "summary.json"
        if not summary.is_file():
            raise CLIError(f"--from-run: no summary.json in {out} (run gpnarx reproduce {args.system} --out {out})")
        ran = json.loads(summary.read_text()).get("system")
        if ran != args.system:
            raise CLIError(f"--from-run: {out} holds a {ran} run, not {args.system}")
        render_from_run(out, args.docs, write_out=False)  # the run folder keeps the page its run wrote
        return {"system": args.system, "out": out, "docs": args.docs}
    log = None if args.json else (lambda m: print(m, file=sys.stderr, flush=True))
    s = reproduce(args.system, out, quick=args.quick, jobs=args.jobs, scheduler=args.scheduler, mc_paths=args.mc,
                  log=log, progress=not args.json, docs_page=args.docs,
                  table_mc=args.table_mc)
    keep = ("system", "quick", "chosen_lags", "paper_lags", "mc_paths", "bundle", "wall_seconds")
    res = {k: s[k] for k in keep}
    res["records"] = {k: {m: v.get(m) for m in ("role", "use", "fit", "fit_clean", "coverage", "coverage_latent")}
                      for k, v in s["records"].items()}
    if "novelty" in s:
        res["novelty_rates"] = s["novelty"]["rates"]
    if "real_table" in s:
        res["real_table_checks"] = s["real_table"]["checks"]
    res["out"] = out
    return res


def run_study(args):
    """A study of the checkout's studies/ folder with its own arguments; CLIError from an installed wheel."""
    from gpnarx.cli.errors import CLIError
    from gpnarx.training.checkout import CheckoutRequired
    from gpnarx.training.checkout import run_study as run

    try:
        rc = run(args.system, args.study_args)
    except CheckoutRequired as e:
        raise CLIError(str(e)) from None
    if rc:
        raise CLIError(f"the study {args.system} failed (exit {rc})")
    return {"study": args.system, "args": args.study_args} if args.json else None
