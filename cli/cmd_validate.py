"""``gpnarx validate --model NAME[:VERSION] RECORD``: how well a model holds on a measured record.

The free run's fit (eq. 14) and band coverage, as ``gpnarx predict`` scores them; the one-step-ahead
(eqs. 8-9) fit and band coverage; the fits by prediction horizon k; and the residual tests of the one-step
residuals (``model.residual_tests``: their autocorrelation at lags 1..L and cross-correlation with the input at
-L..L, with 99 % limits, the share of lags outside them, Ljung-Box and the cross portmanteau). A model whose
residuals still correlate with the input has not learnt the dynamics, however good its fit.

``k_step_fits``: the fit (eq. 14) of the k-step-ahead prediction (``predict`` with ``horizon`` k: the run restarted
from the measured outputs every k samples) at k = 1, 8, 64 and 512, by the free run's method, on every sample after
the record's first ny (k = 1 is eqs. 8-9 at the measured lags: the one-step fit, scored from sample ny rather
than the one-step check's first row max(ny, nu - 1)), and the free run's own (from the record's start rule).

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

from gpnarx.cli.cmd_predict import _common
from gpnarx.cli.errors import CLIError, UsageError

#: horizons k of ``k_step_fits`` (besides the free run) [samples]
K_STEP_HORIZONS = (1, 8, 64, 512)


def add_parser(sub):
    p = sub.add_parser("validate", help="free-run and one-step fit and coverage, fits by horizon, and the residual "
                                        "tests (whiteness, input cross-correlation) of a model on a measured record")
    _common(p)
    p.add_argument("--confidence", type=float, default=0.99,
                   help="band level, and the residual tests' confidence limits and verdicts (default 0.99)")
    p.add_argument("--start", choices=("rest", "measured"), default="rest",
                   help="initial state of the free run: 'rest' (default) or 'measured' (the record's first ny "
                        "measured outputs)")
    p.add_argument("--lags", type=int, default=None,
                   help="lags of the residual tests: autocorrelation 1..L, cross-correlation -L..L (default 25, "
                        "as MATLAB resid)")
    p.set_defaults(func=run_validate)


def _load(args):
    """The record (with its measured y: refused otherwise, before a default registry is built), the
    bundle and the Monte Carlo paths, as ``cmd_predict.load`` has them."""
    from gpnarx.cli.cmd_predict import check_fs, load_model, mc_paths, parse_window, read_cli_record

    mc_paths(args.mc)
    window = parse_window(args.window) if args.window else None
    rec = read_cli_record(args.record, args.fs)
    if rec.y is None:
        raise CLIError(f"{args.record}: validate needs the record's measured output y")
    bundle = load_model(args)
    if window:
        rec = rec.window(*window)
    rec = check_fs(rec, bundle, args.record)
    return bundle, rec, mc_paths(args.mc, bundle, "predict")


def run_validate(args):
    from gpnarx.cli.cmd_predict import operate
    from gpnarx.model.residual_tests import DEFAULT_LAGS, one_step_check

    lags = DEFAULT_LAGS if args.lags is None else args.lags
    if lags < 1:
        raise UsageError(f"--lags must be a positive number of lags, got {lags}")
    if not 0.0 < args.confidence < 1.0:
        raise UsageError(f"--confidence must be in (0, 1), got {args.confidence}")
    bundle, rec, mc = _load(args)
    method = args.method or bundle.default_method("predict")
    a = operate("predict", bundle, rec, mc=mc, seed=args.seed, confidence=args.confidence, method=method,
                start=args.start, backend=args.backend, record=args.record)
    try:
        one = one_step_check(bundle.model, rec.u, rec.y, lags=lags, confidence=args.confidence, with_std=True)
    except ValueError as exc:  # a record too short for the lags, a gap
        raise CLIError(f"{args.record}: {exc}") from None
    free = {k: a.metrics[k] for k in ("fit", "rmse", "coverage", "band_width")}
    tests = one.pop("residual_tests")
    fits = {}
    for k in K_STEP_HORIZONS:  # a horizon at least the record's predicted length is the measured-start free run
        ks = operate("predict", bundle, rec, mc=mc, seed=args.seed, confidence=args.confidence, method=method,
                     backend=args.backend, record=args.record, horizon=k)
        fits[str(k)] = ks.metrics["fit"]
    fits["free_run"] = free["fit"]
    auto, cross = tests["autocorrelation"], tests["cross_correlation"]
    return {
        "model": bundle.name, "version": bundle.version, "record": args.record, "n": rec.n, "start": args.start,
        "method": method, "mc_paths": mc, "confidence": args.confidence,
        "free_run": free,
        "one_step": one,
        "k_step_fits": fits,
        "residuals": {"white": auto["white"], "independent": cross["independent"], "passed": tests["passed"],
                      "lags": tests["lags"], "limit": tests["limit"],
                      "autocorrelation_outside_share": auto["outside_share"],
                      "ljung_box_p": auto["ljung_box"]["p_value"],
                      "cross_correlation_outside_share": cross["outside_share"],
                      "cross_portmanteau_p": cross["portmanteau"]["p_value"]},
        "residual_tests": tests,
    }
