"""The CLI's user error type."""


class CLIError(Exception):
    """An error the user can fix; printed as one line on stderr, exit code 2."""
