"""Reading a study step's result files (a run's cross-play summary, a comparison's, an over-training point):
one rule for the runner, which decides from them whether a step is done, and the report, which shows them."""

from __future__ import annotations

from pathlib import Path

from ocv2 import boundedjson


def read_result(path: Path, required: tuple[str, ...] = ()) -> tuple[dict, str | None]:
    """A step's result file as (data, None), or ({}, why it cannot be used): missing, unreadable, not a JSON
    object or without the ``required`` keys (a file another command wrote over it)."""
    try:
        data = boundedjson.loads(Path(path).read_text())
    except FileNotFoundError:
        return {}, f"{path} is missing"
    except (OSError, ValueError) as error:  # ValueError: not JSON (UnicodeDecodeError, JSONDecodeError, too deep)
        return {}, f"{path} is unreadable ({error})"
    if not isinstance(data, dict):
        return {}, f"{path} holds a JSON {type(data).__name__}, not a result"
    missing = [key for key in required if key not in data]
    if missing:
        return {}, f"{path} is not a result of this step (no {', '.join(missing)})"
    return data, None
