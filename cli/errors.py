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
