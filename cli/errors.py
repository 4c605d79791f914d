"""The CLI's user error types and exit codes.

``CLIError``: the command line was well formed but the work could not be done (unknown model,
unreadable record, missing registry, a record that does not fit the model): exit code 1.
``UsageError``: the command line itself is wrong (an option's value, a missing or conflicting
option): exit code 2, as argparse uses for its own usage errors.
"""

#: exit code of a runtime error (``CLIError`` and the ``ValueError``/``OSError`` family a command raises)
EXIT_RUNTIME = 1
#: exit code of a usage error (``UsageError``, argparse)
EXIT_USAGE = 2


class CLIError(Exception):
    """An error the user can fix that is not in the command line itself; one line on stderr, exit code 1."""

    exit_code = EXIT_RUNTIME


class UsageError(CLIError):
    """A wrong command line (option value, missing or conflicting option); one line on stderr, exit code 2."""

    exit_code = EXIT_USAGE


#: the command-line option of each request field an operation may refuse (``operations``)
OPTION_OF = {"mc_paths": "--mc", "confidence": "--confidence", "method": "--method", "backend": "--backend",
             "seed": "--seed"}
#: request fields that come from the record file
RECORD_FIELDS = ("u", "y", "y0", "fs")


def operation_error(exc, record: str | None = None) -> CLIError:
    """The CLI error of a refused operation (``operations.OperationError``): a refused option value is a
    usage error naming the option (exit code 2); anything else, such as a record that does not fit the model
    or a model without what the operation needs, a runtime error (exit code 1), prefixed by the record's name
    when the record is to blame."""
    if exc.field in OPTION_OF:
        return UsageError(f"{OPTION_OF[exc.field]}: {exc.detail}")
    if exc.field == "start":
        return CLIError(f"--start measured needs the record's measured output y{f' ({record})' if record else ''}")
    if exc.field in RECORD_FIELDS and record:
        return CLIError(f"{record}: {exc.detail}")
    return CLIError(exc.detail)
