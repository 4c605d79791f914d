"""``gpnarx validate --model NAME[:VERSION] RECORD``: how well a model holds on a measured record.

The free run's fit (eq. 14) and band coverage, as ``gpnarx predict`` scores them; the one-step-ahead
(eqs. 8-9) fit and band coverage; the fits by prediction horizon k; and the residual tests of the one-step
residuals (``model.residual_tests``: their autocorrelation at lags 1..L and cross-correlation with the input at
-L..L, with 99 % limits, the share of lags outside them, Ljung-Box and the cross portmanteau). A model whose
residuals still correlate with the input has not learnt the dynamics, however good its fit.

k-step-ahead prediction (issue 53) is not built yet: ``k_step_fits`` holds k = 1 (the one-step fit) and the
free run; the horizons 8, 64 and 512 are in it as null until it is.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

from gpnarx.cli.cmd_predict import _common
from gpnarx.cli.errors import CLIError, UsageError

#: horizons k of ``k_step_fits`` (besides the free run); only k = 1 is computed until k-step prediction exists
K_STEP_HORIZONS = (1, 8, 64, 512)
#: what ``k_step_note`` says while the horizons above 1 are pending
K_STEP_PENDING = ("k = 8, 64, 512: k-step-ahead prediction is not built yet (issue 53); k = 1 is the one-step "
                  "prediction (eqs. 8-9), free_run the free run from the record's start rule")


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
    fits = {str(k): (one["fit"] if k == 1 else None) for k in K_STEP_HORIZONS}
    fits["free_run"] = free["fit"]
    auto, cross = tests["autocorrelation"], tests["cross_correlation"]
    return {
        "model": bundle.name, "version": bundle.version, "record": args.record, "n": rec.n, "start": args.start,
        "method": method, "mc_paths": mc, "confidence": args.confidence,
        "free_run": free,
        "one_step": one,
        "k_step_fits": fits,
        "k_step_note": K_STEP_PENDING,
        "residuals": {"white": auto["white"], "independent": cross["independent"], "passed": tests["passed"],
                      "lags": tests["lags"], "limit": tests["limit"],
                      "autocorrelation_outside_share": auto["outside_share"],
                      "ljung_box_p": auto["ljung_box"]["p_value"],
                      "cross_correlation_outside_share": cross["outside_share"],
                      "cross_portmanteau_p": cross["portmanteau"]["p_value"]},
        "residual_tests": tests,
    }
