"""Live progress: a population's training (updates, env steps/s, recent return, ETA, restarts) and job counts
(cross-play).

On a terminal a rich bar on stderr; otherwise (logs, CI, a script) one INFO record of this module's logger
per chunk or wave, which the ``ocv2`` command line shows on stderr unless ``-q``.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Sequence

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

log = logging.getLogger(__name__)


def _bar(*columns) -> Progress | None:
    """A rich bar on stderr when stderr is a terminal (stdout stays for results), else None."""
    if not sys.stderr.isatty():
        return None
    return Progress(*columns, console=Console(stderr=True))


class PopulationProgress:
    """A rich progress bar on a terminal; one plain line per chunk otherwise (logs, CI)."""

    def __init__(
        self,
        label: str,
        num_seeds: int,
        total_updates: int,
        steps_per_update: int,
        enabled: bool = True,
        details: Sequence[str] = (),
    ):
        """``details``: more lines of the run's header, after the first (e.g. where the seeds train)."""
        self.label, self.num_seeds, self.total = label, num_seeds, total_updates
        self.details = list(details)
        self.steps_per_update = steps_per_update
        self.enabled = enabled
        self.steady: tuple[int, float] | None = None  # (update, time) at the end of the first chunk
        self._bar = None
        self._task = None

    def __enter__(self):
        if self.enabled:
            log.info(header(self.label, self.num_seeds, self.total, self.steps_per_update))
            for line in self.details:
                log.info(f"  {line}")
            self._bar = _bar(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"),
                TimeRemainingColumn(),
            )
        if self._bar is not None:
            self._bar.__enter__()
            self._task = self._bar.add_task(self.label, total=self.total, info="compiling...")
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False

    def note(self, text: str) -> None:
        if self._bar is not None:
            self._bar.update(self._task, info=text)
        elif self.enabled:
            log.info(f"  {text}")

    def advance_to(self, update: int, rows, steps_per_s: float | None = None, restarts: int = 0) -> None:
        """``rows``: the metrics.csv rows of the chunk that ended at ``update`` (None: just move the bar).

        The first chunk of a process starts up: it compiles its programs, or traces them and loads them from a cache
        (a second run of an equal config in one process only looks them up), and an SA run collects its states first.
        So its time says little of the rest's: on a 2-core CPU an SA resume's first chunk ran at a third of the later
        rate. The ETA is measured from the end of that chunk on; the first chunk's line says so instead of guessing."""
        now = time.perf_counter()
        if rows is None:
            if self._bar is not None:
                self._bar.update(self._task, completed=update)
            return
        sparse, shaped = _latest(rows, "sparse_return"), _latest(rows, "shaped_return")
        first = self.steady is None
        rate = f"{steps_per_s or 0:,.0f} env steps/s" + (" (first chunk, with start-up)" if first else "")
        info = f"{rate}  return {_fmt(sparse)}  shaped {_fmt(shaped)}"
        if restarts:
            info += f"  worker restarts {restarts}"
        if first:
            self.steady = (update, now)
            eta = "after the next chunk (this one started up)" if update < self.total else duration(0)
        else:
            done, elapsed = update - self.steady[0], now - self.steady[1]
            eta = duration(elapsed / done * (self.total - update) if done else math.nan)
        if self._bar is not None:
            self._bar.update(self._task, completed=update, info=info)
        elif self.enabled:
            log.info(f"  update {update}/{self.total}  {info}  ETA {eta}")


class Bar:
    """A rich progress bar over jobs on a terminal; one line per wave otherwise (logs, CI); or nothing."""

    def __init__(self, label: str, enabled: bool = True, unit: str = "jobs"):
        self.unit = unit
        self.label, self.enabled, self._bar, self._task, self.started = label, enabled, None, None, time.perf_counter()
        self.done = 0

    def __enter__(self):
        if self.enabled:
            self._bar = _bar(
                TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()
            )
        if self._bar is not None:
            self._bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False

    def __call__(self, done: int, total: int) -> None:
        """``done`` more of ``total`` jobs finished (0 first: the bar appears)."""
        self.done += done
        if self._bar is not None:
            if self._task is None:
                self._task = self._bar.add_task(self.label, total=total)
            self._bar.update(self._task, completed=self.done)
        elif self.enabled and done:
            elapsed = time.perf_counter() - self.started
            eta = f", ETA {duration(elapsed / self.done * (total - self.done))}" if self.done < total else ""
            log.info(f"  {self.label}: {self.done}/{total} {self.unit} ({elapsed:.0f} s{eta})")


def header(label: str, num_seeds: int, num_updates: int, steps_per_update: int) -> str:
    """The first line of a run, worded as ``ocv2 validate`` describes a config."""
    return (
        f"{label}: {num_seeds} seeds x {num_updates} updates x {steps_per_update:,} "
        f"= {num_updates * steps_per_update:,} env steps per seed"
    )


def _latest(rows, name: str) -> np.ndarray:
    """Each seed's value of ``name`` at its last row ("" -- no episode finished yet -- is NaN)."""
    last = {}
    for row in rows:
        last[row["seed"]] = row[name]
    return np.asarray([np.nan if v == "" else float(v) for v in last.values()], np.float64)


def _fmt(values: np.ndarray) -> str:
    values = values[~np.isnan(values)]
    if values.size == 0:
        return "n/a (no episode finished yet)"
    return f"{values.mean():.1f}+-{values.std():.1f}"


def duration(seconds: float | None) -> str:
    """``1h05m`` or ``4m07s``, rounded to the nearest minute or second (as docs/RESULTS.md writes the same times); ``?``
    for an unknown (None or NaN) time."""
    if seconds is None or math.isnan(seconds):
        return "?"
    # half up, each from the time itself (round() would take halves to the even number, and rounding twice drifts)
    if math.floor(seconds + 0.5) < 3600:
        whole = math.floor(seconds + 0.5)
        return f"{whole // 60}m{whole % 60:02d}s"
    minutes = math.floor(seconds / 60 + 0.5)
    return f"{minutes // 60}h{minutes % 60:02d}m"
