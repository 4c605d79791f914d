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
    "gpnarx.cli.cmd_validate",
    "gpnarx.cli.cmd_stream",
    "gpnarx.cli.cmd_calibrate",
    "gpnarx.cli.cmd_update",
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
    """argparse parser whose usage errors are one line on stderr and exit code 2. An option it does not know is
    named as such (with the closest known option) before any missing required one: ``--modle`` is an
    unrecognized argument, not a missing ``--model``."""

    _args: list = []

    def parse_known_args(self, args=None, namespace=None):
        self._args = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def _unknown_options(self) -> list[str]:
        """The option-like words of this parser's arguments that name none of its options (an abbreviation of
        one counts as known, as argparse takes it)."""
        known = list(self._option_string_actions)
        out = []
        for arg in self._args:
            if arg == "--":
                break
            if not arg.startswith("--") or len(arg) < 3:
                continue
            word = arg.split("=", 1)[0]
            if word not in known and not any(k.startswith(word) for k in known if k.startswith("--")):
                out.append(word)
        return out

    def _unrecognized(self, words: list[str]) -> str:
        import difflib

        options = [k for k in self._option_string_actions if k.startswith("--")]
        parts = []
        for w in words:
            near = difflib.get_close_matches(w, options, n=1, cutoff=0.6)
            parts.append(w + (f" (did you mean {near[0]}?)" if near else ""))
        return f"unrecognized argument{'s' if len(words) > 1 else ''}: {', '.join(parts)}"

    def _command_parser(self) -> "_Parser":
        """The parser of the command named in the arguments (the top-level parser reports the arguments its
        command's parser left over), else this one."""
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                for arg in self._args:
                    if arg in action.choices:
                        return action.choices[arg]
        return self

    def error(self, message):  # noqa: D401
        parser = self
        if message.startswith("the following arguments are required") or message.startswith("unrecognized arguments"):
            parser = self._command_parser()
            unknown = parser._unknown_options()
            if unknown:
                message = parser._unrecognized(unknown)
        raise UsageError(f"{message} (see '{parser.prog} --help')")


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


#: significant digits of a number in the human-readable answer (``--json`` keeps every digit)
HUMAN_DIGITS = 6
#: longest list printed whole in the human-readable answer; a longer one is summarised
HUMAN_LIST = 8


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _human(value) -> str:
    """One value of an answer as the human-readable summary prints it: numbers to ``HUMAN_DIGITS`` significant
    digits, a long numeric array as its length and range (the values themselves with ``--json``)."""
    if value is None or isinstance(value, (bool, np.bool_, str)):
        return str(value)
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.{HUMAN_DIGITS}g}"
    if isinstance(value, np.ndarray):
        if value.ndim == 1 and value.size > HUMAN_LIST and value.dtype.kind in "iuf":  # as below, in numpy
            finite = value[np.isfinite(value)].astype(float)
            span = (f"from {_human(float(finite.min()))} to {_human(float(finite.max()))}" if finite.size
                    else "none finite")
            return f"{value.size} values {span} (--json for all)"
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        if len(value) <= HUMAN_LIST:
            return "[" + ", ".join(_human(v) for v in value) + "]"
        if all(v is None or _is_number(v) for v in value):
            finite = [float(v) for v in value if v is not None and np.isfinite(v)]
            span = (f"from {_human(min(finite))} to {_human(max(finite))}" if finite else "none finite")
            return f"{len(value)} values {span} (--json for all)"
        return f"{len(value)} items (--json for all)"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_human(v)}" for k, v in value.items()) + "}"
    return str(value)


def _print_human(result: dict) -> None:
    for key, value in result.items():
        print(f"{key}: {_human(value)}")


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
