"""``ConfigError``: every configuration problem, each naming its key (and file, or ``--set``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: Problems caused by a command-line override start with this; they name the override, not the file.
SET_PREFIX = "--set "


class ConfigError(ValueError):
    """Configuration problems; the message names the key (and file, or ``--set``) at fault.

    ``problems`` lists every problem found (``ocv2 validate`` prints them all); the message is the first
    one, followed by how many more there are.
    """

    def __init__(self, message: str | Sequence[str], partial: Any = None):
        self.problems = [message] if isinstance(message, str) else list(message)
        self.partial = partial  # what could be parsed (bad keys at their defaults), to check the rest against
        first = self.problems[0]
        more = len(self.problems) - 1
        super().__init__(
            first if not more else f"{first} (and {more} more problem{'s' * (more > 1)}; ocv2 validate lists them all)"
        )

    def prefixed(self, prefix: str) -> ConfigError:
        """The same problems with ``prefix`` (e.g. the file) in front of each, except those of ``--set``
        overrides, which did not come from the file."""
        return ConfigError(
            [problem if problem.startswith(SET_PREFIX) else f"{prefix}: {problem}" for problem in self.problems]
        )
