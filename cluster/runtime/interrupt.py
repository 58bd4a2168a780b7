"""Ctrl-C (or SIGTERM, under the command line) while a training chunk runs: jitted in this process (the local
backend), or in Ray actors the driver waits for (``RayWorkers.call``, the same answers).

Python runs a signal handler only between bytecodes of the main thread, so a main thread blocked in
XLA (``np.asarray`` of a chunk's results) hears Ctrl-C only when the chunk ends: up to tens of minutes.
``ChunkWait`` instead polls ``jax.Array.is_ready`` with short sleeps, between which its own SIGINT
handler runs at once:

- the first Ctrl-C says what is running and lets that chunk finish: ``stop_requested`` tells the caller
  to save it and stop (the coordinator records the chunk, then raises ``KeyboardInterrupt``);
- a second Ctrl-C stops at once with ``ChunkAbandoned``. The chunk keeps running on XLA's threads and a
  normal interpreter exit would wait for it, so the command line ends the process with ``os._exit``
  (``exit_now``) after its own cleanup; the run keeps its last saved checkpoint, and ``--resume``
  continues from there.

SIGTERM is answered the same way where it raises ``KeyboardInterrupt`` (the command line makes it so: a job
started in the background ignores SIGINT, so SIGTERM is how a script or a service manager stops a run
gracefully). An interrupt that lands outside such a wait -- while a program compiles, during cross-play --
may leave XLA work running; the command line then ends the process with ``exit_now`` too, because an
interpreter shutting down under running XLA threads can abort ("pure virtual method called").
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable

import jax

from cluster.runtime.progress import duration

log = logging.getLogger(__name__)

POLL_S = 0.05  # Ctrl-C is answered within this; the chunks it waits for take seconds to minutes


class ChunkAbandoned(KeyboardInterrupt):
    """A second Ctrl-C: a jitted computation still runs, so the process must exit without waiting."""


class StoppedAfterChunk(KeyboardInterrupt):
    """The first Ctrl-C, raised once the chunk it let finish is on disk: no XLA work is left running."""


def jax_started() -> bool:
    """Whether this process has started a JAX backend (so XLA threads may be running)."""
    try:
        from jax._src import xla_bridge  # no public API says this; if it moves, assume started

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return True


def _signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def _ready(tree) -> bool:
    return all(leaf.is_ready() for leaf in jax.tree.leaves(tree) if isinstance(leaf, jax.Array))


class ChunkWait:
    """``wait = ChunkWait(what, resume_hint); out = wait.until_ready(f(...)); save(out)``, then stop if
    ``wait.stop_requested``.

    ``what`` names the chunk in the first Ctrl-C's message ("updates 93-124"); ``resume_hint`` says where
    a second Ctrl-C leaves the run ("resuming continues from update 92").
    """

    def __init__(self, what: str, resume_hint: str):
        self.what, self.resume_hint = what, resume_hint
        self.stop_requested = False  # a first Ctrl-C arrived: save this chunk, then stop
        self._first = signal.SIGINT  # the signal that asked for the stop
        self._started = time.monotonic()  # when the chunk's wait began (the warning says how long it has run)
        self._warned = False

    def until_ready(self, tree):
        """Return ``tree`` once every array in it is computed, answering Ctrl-C meanwhile (see module doc)."""
        self.until(lambda: _ready(tree))
        return tree

    def until(self, done: Callable[[], bool]) -> None:
        """Return once ``done()`` (polled every ``POLL_S``) is true, answering Ctrl-C meanwhile (``answering``)."""
        with self.answering():
            while not done():
                self.poll()

    @contextlib.contextmanager
    def answering(self):
        """Answer Ctrl-C (and SIGTERM) as the module doc says for as long as the block runs: a jitted chunk in this
        process (``until``), or every result of a chunk of Ray actors, restarts included (``RayWorkers.call``), so
        a signal that lands between two results is answered the same way.

        SIGINT and SIGTERM are taken over only where Python's own handler (``KeyboardInterrupt``) is in place:
        a job started in the background ignores SIGINT, SIGTERM ends a process unless the command line made it
        a Ctrl-C, and a host process (a Ray worker) may have its own.
        """
        main_thread = threading.current_thread() is threading.main_thread()  # only it can set a handler
        taken = [
            signum
            for signum in (signal.SIGINT, signal.SIGTERM)
            if main_thread and signal.getsignal(signum) is signal.default_int_handler
        ]
        # A handler, not ``except KeyboardInterrupt``: a second press that lands while the first one's
        # message is written must still stop at once, not escape as a plain KeyboardInterrupt whose
        # exit then waits for the chunk.
        previous = {signum: signal.signal(signum, self._pressed) for signum in taken}
        try:
            yield self
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)

    def poll(self) -> None:
        """One wait of ``POLL_S`` inside ``answering``; says once, after a first signal, what it lets finish."""
        if self.stop_requested and not self._warned:
            self._warned = True
            name = _signal_name(self._first)
            log.warning(
                "%s: letting %s finish (running for %s) so it is saved, then stopping; "
                "%s again to stop now and lose it (%s)",
                name,
                self.what,
                duration(time.monotonic() - self._started),
                "press Ctrl-C" if name == "Ctrl-C" else f"send {name} or press Ctrl-C",
                self.resume_hint,
            )
        time.sleep(POLL_S)

    def _pressed(self, signum, frame) -> None:
        if self.stop_requested:
            log.warning("second %s: stopping now without %s; %s", _signal_name(signum), self.what, self.resume_hint)
            raise ChunkAbandoned
        self.stop_requested, self._first = True, signum


def exit_now(code: int) -> None:  # pragma: no cover - ends the process; tested in a subprocess
    """Flush what was printed and end the process without waiting for abandoned XLA work."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
