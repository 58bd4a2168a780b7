"""docs/BENCHMARKS.md is shared by every bench script: each owns the block between its two marks."""

from __future__ import annotations

import os
import re


def write_section(path: str, block: str, start: str, end: str) -> None:
    """Replace the ``start``..``end`` block of ``path`` with ``block`` (which includes both marks).

    The rest of the file is kept; a missing block is appended and a missing file is created.
    """
    if os.path.exists(path):
        with open(path) as handle:
            text = handle.read()
        pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.S)
        if pattern.search(text):
            text = pattern.sub(lambda _m: block, text, count=1)
        else:
            text = text.rstrip("\n") + "\n\n" + block + "\n"
    else:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        text = "# Benchmarks\n\n" + block + "\n"
    with open(path, "w") as handle:
        handle.write(text)


def publish(block: str, path: str, start: str, end: str) -> None:
    """Print the block; write it into ``path`` unless ``path`` is empty (``--out ''``)."""
    print(block)
    if path:
        write_section(path, block, start, end)
