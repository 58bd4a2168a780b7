"""The checks by name: ``@check("NAME")`` files a function under the name of its span on the page,
``<!-- check:NAME -->``. The modules of checks register theirs when imported; check_results.py imports them all."""

from __future__ import annotations

CHECKS: dict = {}


def check(name: str):
    def register(function):
        CHECKS[name] = function
        return function

    return register


L = None  # a label: present in the span, not compared
