"""Exit codes and the error type every ``ocv2`` subcommand raises for problems the user can fix.

Its own module so that ``python -m cluster.cli`` (where the CLI module runs as ``__main__``) and the
subcommand modules share one ``CLIError`` class.
"""

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


class CLIError(Exception):
    """A problem to report to the user as one line on stderr, with an exit code."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code
