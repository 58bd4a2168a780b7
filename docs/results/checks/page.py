"""Reading the page: the tagged spans of docs/RESULTS.md, the numbers a span writes, and whether a written number
matches a recomputed one at the precision it is written (check_results.py's docstring gives the rules)."""

from __future__ import annotations

import re

SPAN = re.compile(r"<!--\s*check:([\w.-]+)\s*-->(.*?)<!--\s*/check\s*-->", re.S)
TAG = re.compile(r"<!--\s*/?check[^>]*-->")
NUMBER = re.compile(r"-?\d+(?:,\d{3})*(?:\.\d+)?")
NOT_NUMBERS = [
    re.compile(r"\d\+\d\+\d"),  # recipe names
    re.compile(r"95 %"),  # the interval level
    re.compile(r"\bseat \d\b"),  # seat 0, seat 1: labels
    re.compile(r"\[[^\]]*\]\([^)]*\)"),  # markdown links
]


def read_numbers(text: str) -> list[str]:
    """The numbers of one span as written (see the module docstring for what counts)."""
    lines, table_started = [], False
    for line in text.split("\n"):
        stripped = line.strip()
        if stripped.startswith("|"):
            if not table_started:  # header row
                table_started = True
                continue
            if re.fullmatch(r"[|\s:-]+", stripped):  # separator row
                continue
            line = stripped[1:].split("|", 1)[1] if stripped.count("|") > 1 else ""  # drop the label cell
        else:
            table_started = False
        lines.append(line)
    text = "\n".join(lines)
    for pattern in NOT_NUMBERS:
        text = pattern.sub(" ", text)
    found = []
    for match in NUMBER.finditer(text):
        start, token = match.start(), match.group()
        before = text[start - 1] if start > 0 else " "
        after = text[match.end()] if match.end() < len(text) else " "
        if token.startswith("-") and (before.isdigit() or before == "."):
            token = token[1:]  # a range "a-b", not a sign
        elif before.isalpha() or before in "_.":
            continue  # inside an identifier such as seed_0 or sp10
        if (after.isalpha() and after not in "Mx") or after == "_":
            continue
        found.append(token)
    return found


def decimals(token: str) -> int:
    return len(token.split(".")[1]) if "." in token else 0


def matches(token: str, value: float) -> bool:
    written = float(token.replace(",", ""))
    return abs(written - value) <= 0.5 * 10 ** -decimals(token) + 1e-6
