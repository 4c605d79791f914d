"""The ``gpnarx`` console script.

Each subcommand lives in its own module exposing ``add_parser(subparsers)`` which registers the
subcommand and sets ``func`` to a callable ``run(args) -> dict | None``. A returned dict is printed as
one JSON object on stdout when ``--json`` is given (else a short human summary); a command may set
``args.exit_code`` (``predict-many``: 1 when some record failed). Exit codes: 2 for a usage error
(argparse, ``UsageError``: the command line itself is wrong), 1 for a runtime error (``CLIError``,
``ValueError``, ``OSError``, ``KeyError``, ``LookupError``, ``ImportError`` raised by a command: unknown
model, unreadable record, an optional package of an extra not installed, ...), each one line on stderr.
``gpnarx --version`` prints the package version. Ctrl-C ends a command with exit code 130 and SIGTERM (a
scheduler or ``kill``) with 143, each raised in the command like an interrupt, so what it started stops with it
(joblib's worker processes are ended, not left computing their current task). SIGTERM is handled so only where
``main`` is the process's entry point (called without ``argv``); ``main([...])`` called in-process leaves it alone.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys

import numpy as np

from gpnarx import __version__
from gpnarx.cli.errors import EXIT_RUNTIME, EXIT_USAGE, CLIError, UsageError
from gpnarx.storage.jsonsafe import dumps_json

# Subcommand modules, in the order shown by --help.
COMMAND_MODULES = [
    "gpnarx.cli.cmd_simulate",
    "gpnarx.cli.cmd_lags",
    "gpnarx.cli.cmd_train",
    "gpnarx.cli.cmd_predict",
    "gpnarx.cli.cmd_predict_many",
    "gpnarx.cli.cmd_stream",
    "gpnarx.cli.cmd_calibrate",
    "gpnarx.cli.cmd_serve",
    "gpnarx.cli.cmd_alias",
    "gpnarx.cli.cmd_build",
    "gpnarx.cli.cmd_reproduce",
]


class Terminated(KeyboardInterrupt):
    """SIGTERM during a command, raised in it like Ctrl-C so that what it runs unwinds and cleans up."""


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM raises ``Terminated`` in the main thread while the block runs (elsewhere: signals untouched)."""
    def raise_terminated(signum, frame):
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, raise_terminated)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Parser(argparse.ArgumentParser):
    """argparse parser whose usage errors are one line on stderr and exit code 2."""

    def error(self, message):  # noqa: D401
        raise UsageError(f"{message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="gpnarx",
        description="GP-NARX surrogate of hysteretic bolted structures: simulate, train, predict, serve.",
    )
    parser.add_argument("--json", action="store_true", help="print one machine-readable JSON object on stdout")
    parser.add_argument("--version", action="version", version=f"gpnarx {__version__}",
                        help="print the package version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for mod_name in COMMAND_MODULES:
        importlib.import_module(mod_name).add_parser(sub)
    return parser


def _print_human(result: dict) -> None:
    for key, value in result.items():
        if isinstance(value, (list, np.ndarray)) and len(value) > 8:
            continue
        print(f"{key}: {value}")


def main(argv: list[str] | None = None) -> int:
    # SIGTERM is the process's: taken over only where main is its entry point (the console script and
    # ``python -m gpnarx`` call it without argv), not when a program or a test calls main([...]) in-process
    entry_point = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    # accept --json anywhere on the line
    as_json = "--json" in argv
    argv = [a for a in argv if a != "--json"]
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except CLIError as exc:
        print(f"gpnarx: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except SystemExit as exc:  # --help, --version
        return int(exc.code or 0)
    args.json = as_json
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        with _terminate_as_interrupt() if entry_point else contextlib.nullcontext():
            result = args.func(args)
    except Terminated:
        print("gpnarx: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("gpnarx: interrupted", file=sys.stderr)
        return 130
    except (CLIError, ValueError, OSError, KeyError, LookupError, ImportError) as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if isinstance(exc, KeyError):
            msg = f"missing key {exc}"
        print(f"gpnarx {args.command}: error: {msg}", file=sys.stderr)
        return getattr(exc, "exit_code", EXIT_RUNTIME)
    if result is not None:
        if as_json:
            sys.stdout.write(dumps_json(result).decode() + "\n")
        else:
            _print_human(result)
    return int(getattr(args, "exit_code", 0))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
