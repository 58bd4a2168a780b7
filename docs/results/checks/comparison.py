"""The page against the checks: every tagged span's numbers beside what its check recomputes."""

from __future__ import annotations

from .page import SPAN, TAG, matches, read_numbers
from .registry import CHECKS

SCRIPT = "check_results.py"  # the checker, named in the error for a tag without a check


def compare(doc: str) -> tuple[list[tuple], list[str]]:
    """[(name, index, written, recomputed, ok)], [errors]"""
    rows, errors, seen = [], [], set()
    for match in SPAN.finditer(doc):
        name, text = match.group(1), match.group(2)
        if "<!--" in TAG.sub("", text) and "check:" in text:
            errors.append(f"{name}: a check span inside another")
        line = doc.count("\n", 0, match.start()) + 1
        if name in seen:
            errors.append(f"{name} (line {line}): tagged twice")
        seen.add(name)
        if name not in CHECKS:
            errors.append(f"{name} (line {line}): no check of that name in {SCRIPT}")
            continue
        written = read_numbers(TAG.sub("", text))
        expected = [None if v is None else float(v) for v in CHECKS[name]()]
        if len(written) != len(expected):
            errors.append(
                f"{name} (line {line}): the span writes {len(written)} numbers {written}, the check recomputes {len(expected)}"
            )
            continue
        for k, (token, value) in enumerate(zip(written, expected)):
            ok = value is None or matches(token, value)
            rows.append((name, k, token, value, ok))
    for name in CHECKS:
        if name not in seen:
            errors.append(f"{name}: no <!-- check:{name} --> span on the page")
    return rows, errors
