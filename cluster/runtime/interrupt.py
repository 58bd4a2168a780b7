"""Ctrl-C while a jitted training chunk runs in this process (the local backend).

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
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time

import jax

from cluster.runtime.progress import duration

log = logging.getLogger(__name__)

POLL_S = 0.05  # Ctrl-C is answered within this; the chunks it waits for take seconds to minutes


class ChunkAbandoned(KeyboardInterrupt):
    """A second Ctrl-C: a jitted computation still runs, so the process must exit without waiting."""


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

    def until_ready(self, tree):
        """Return ``tree`` once every array in it is computed, answering Ctrl-C meanwhile (see module doc).

        Ctrl-C is taken over only where Python's own handler (``KeyboardInterrupt``) is in place: a job
        started in the background ignores SIGINT, and a host process (a Ray worker) may have its own.
        """
        started = time.monotonic()
        take_over = (  # only the main thread can set a handler
            threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        )
        # A handler, not ``except KeyboardInterrupt``: a second press that lands while the first one's
        # message is written must still stop at once, not escape as a plain KeyboardInterrupt whose
        # exit then waits for the chunk.
        previous = signal.signal(signal.SIGINT, self._pressed) if take_over else None
        try:
            warned = False
            while not _ready(tree):
                if self.stop_requested and not warned:
                    warned = True
                    log.warning(
                        "Ctrl-C: letting %s finish (running for %s) so it is saved, then stopping; "
                        "press Ctrl-C again to stop now and lose it (%s)",
                        self.what,
                        duration(time.monotonic() - started),
                        self.resume_hint,
                    )
                time.sleep(POLL_S)
        finally:
            if take_over:
                signal.signal(signal.SIGINT, previous)
        return tree

    def _pressed(self, signum, frame) -> None:
        if self.stop_requested:
            log.warning("second Ctrl-C: stopping now without %s; %s", self.what, self.resume_hint)
            raise ChunkAbandoned
        self.stop_requested = True


def exit_now(code: int) -> None:  # pragma: no cover - ends the process; tested in a subprocess
    """Flush what was printed and end the process without waiting for abandoned XLA work."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
