"""JSON from untrusted files and requests, with a bound on how deep it nests.

``json.loads`` recurses once per level: text nested a few thousand deep (a few KB of ``[[[[...``)
raises ``RecursionError``, which is no ``ValueError`` and escapes the callers' error handling; text
that parses just under the interpreter's limit can still break later recursive code (printing,
copying, re-encoding). Every file header, archive record and play message ocv2 reads is a few levels
deep, so ``loads`` refuses anything deeper than ``max_depth`` with a ``ValueError``.
"""

from __future__ import annotations

import json

#: Deepest nesting accepted by default: ocv2's own JSON nests at most a handful of levels.
MAX_DEPTH = 32


class JSONDepthError(ValueError):
    """JSON text nested deeper than the caller allows."""


def loads(text: str | bytes, max_depth: int = MAX_DEPTH):
    """``json.loads(text)``, refused with ``JSONDepthError`` when arrays/objects nest deeper than ``max_depth``.

    Other malformed text raises ``json.JSONDecodeError`` (a ``ValueError``), as ``json.loads`` does.
    """
    try:
        value = json.loads(text)
    except RecursionError:
        raise JSONDepthError(f"JSON nested deeper than {max_depth} levels") from None
    if depth(value, max_depth + 1) > max_depth:
        raise JSONDepthError(f"JSON nested deeper than {max_depth} levels")
    return value


def depth(value, stop: int | None = None) -> int:
    """Nesting depth of a parsed JSON value (a scalar is 0, ``[]`` is 1), without recursion; the walk
    ends as soon as ``stop`` levels are found."""
    deepest, pending = 0, [(value, 0)]
    while pending:
        item, level = pending.pop()
        if isinstance(item, (list, dict)):
            level += 1
            deepest = max(deepest, level)
            if stop is not None and deepest >= stop:
                return deepest
            pending.extend((child, level) for child in (item.values() if isinstance(item, dict) else item))
    return deepest


__all__ = ["MAX_DEPTH", "JSONDepthError", "depth", "loads"]
