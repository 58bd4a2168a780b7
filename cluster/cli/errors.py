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


#: What to do after a full disk, a read-only or vanished folder, unless the command says more
#: (``args.os_error_advice``): every file ocv2 writes is written atomically, so nothing is half-written.
OS_ERROR_ADVICE = "fix the cause (e.g. free disk space, or choose a writable folder) and run the command again"


def os_error_message(error: OSError, advice: str | None = None) -> str:
    """An ``OSError`` as one line: what the system said, the file it said it about, what to do."""
    names = [str(name) for name in (error.filename, error.filename2) if name is not None]
    where = f" ({' -> '.join(names)})" if names else ""
    return f"{error.strerror or error}{where}; {advice or OS_ERROR_ADVICE}"
