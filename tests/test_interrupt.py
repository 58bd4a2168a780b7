"""Real Ctrl-C (SIGINT) while a jitted computation runs: answered at once, and two of them end the process.

The computation here never ends (a ``while_loop`` whose condition stays true), so the test can only pass if
the process exits without waiting for XLA: without ``ChunkWait``'s polling the first SIGINT would never be
heard, and without ``exit_now`` the interpreter's exit would wait forever. What the command line does with
each Ctrl-C (save the chunk, or stop and resume) is tested in tests/test_train_cli.py.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CHILD = textwrap.dedent(
    """
    import logging, signal, sys
    # As in a terminal. A child of a background job (nohup, `&` in a script, some CI runners) starts with
    # SIGINT ignored, and then ChunkWait rightly leaves Ctrl-C alone.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # as the command line makes it
    import jax, jax.numpy as jnp
    from cluster.runtime import interrupt
    from cluster.runtime.interrupt import ChunkAbandoned, ChunkWait, exit_now

    ready = interrupt._ready
    def announce_then_check(tree):  # "waiting" from inside the poll: a Ctrl-C cannot come before it
        if not announced:
            announced.append(print("waiting", flush=True))
        return ready(tree)
    announced = []
    interrupt._ready = announce_then_check

    logging.basicConfig(stream=sys.stderr, format="%(message)s")
    # The matrix product makes the program costly enough that XLA:CPU runs it on its own threads (a
    # scalar-only program would run inline in this thread, as no training chunk does).
    step = lambda c: (jnp.tanh(c[0] @ c[0]), c[1] + 1.0)
    forever = jax.jit(lambda m: jax.lax.while_loop(lambda c: c[1] >= 0.0, step, (m, jnp.float32(0.0))))
    wait = ChunkWait("updates 1-2", "resuming continues from update 0")
    result = forever(jnp.full((256, 256), 0.01))  # returns at once; the loop runs on XLA's threads
    try:
        wait.until_ready(result)
    except ChunkAbandoned:
        print("abandoned", flush=True)
        exit_now(130)
    print("the loop ended?!", flush=True)
    """
)


@pytest.mark.parametrize(
    "signum, name, again",
    [
        (signal.SIGINT, "Ctrl-C", "press Ctrl-C again"),
        (signal.SIGTERM, "SIGTERM", "send SIGTERM or press Ctrl-C again"),
    ],
)
def test_two_real_ctrl_cs_end_a_process_whose_computation_never_ends(signum, name, again):
    """Twice Ctrl-C, or twice SIGTERM (how a job in the background, which ignores SIGINT, is stopped)."""
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    watchdog = threading.Timer(120, child.kill)  # a failure must not hang the suite on a blocked readline
    watchdog.start()
    try:
        assert child.stdout.readline().strip() == "waiting"
        child.send_signal(signum)
        first = child.stderr.readline()  # the first one is answered while the loop still runs
        assert first.startswith(f"{name}: letting updates 1-2 finish") and again in first
        child.send_signal(signum)
        out, err = child.communicate(timeout=60)
    finally:
        watchdog.cancel()
        child.kill()
    assert child.returncode == 130
    assert out.strip() == "abandoned"
    assert f"second {name}: stopping now without updates 1-2; resuming continues from update 0" in err


def test_ctrl_c_is_taken_over_only_where_python_s_own_handler_is_in_place(monkeypatch):
    """A background job (nohup, `&` in a script) ignores SIGINT: the wait must leave it ignored. In a terminal
    it answers Ctrl-C itself while it waits and gives Python's handler back afterwards."""
    import jax.numpy as jnp

    from cluster.runtime import interrupt
    from cluster.runtime.interrupt import ChunkWait

    seen = []
    monkeypatch.setattr(interrupt, "_ready", lambda tree: seen.append(signal.getsignal(signal.SIGINT)) or True)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        wait = ChunkWait("updates 1-2", "resuming continues from update 0")
        wait.until_ready(jnp.zeros(2))
        assert seen == [signal.SIG_IGN] and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        seen.clear()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        wait.until_ready(jnp.zeros(2))
        assert seen == [wait._pressed] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert not wait.stop_requested
    finally:
        signal.signal(signal.SIGINT, previous)
