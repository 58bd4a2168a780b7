"""XLA flags that the running jaxlib knows.

XLA reads ``XLA_FLAGS`` once, when JAX starts its first backend, and a flag it does not know is fatal: it
logs ``Unknown flag in XLA_FLAGS: ...`` and ends the whole process (exit status 1, no Python exception to
catch, no pytest summary, and every subprocess or Ray actor that inherits the variable dies the same way).
Flags come and go between jaxlib releases (0.10.2 knows ``--xla_cpu_use_fusion_emitters``, 0.11.2 does
not), so a flag that is only an optimisation or a safeguard (faster compiles in the tests, GPU determinism)
must be set only where the running jaxlib knows it.

:func:`supported_flags` finds out by asking: it starts ``sys.executable`` with ``XLA_FLAGS`` set to the
candidates and runs one tiny JAX computation on the CPU (``JAX_PLATFORMS=cpu``: the probe never touches or
reserves a GPU, yet XLA parses every flag, GPU ones included, whatever backend starts). A flag is kept when
the probe exits 0; if the candidates together fail, each is probed alone. The answer is cached for the
process. This module does not import JAX, so it can run before JAX starts a backend (pytest's configure
hook, a launcher building the environment of its workers)::

    from population.xla_flags import extend_xla_flags

    flags = extend_xla_flags(os.environ.get("XLA_FLAGS", ""), ["--xla_gpu_deterministic_ops=true"])
    os.environ["XLA_FLAGS"] = flags  # before this process's first JAX computation

A probe costs one Python start and JAX import (1-3 s on a free core).
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from collections.abc import Iterable

__all__ = ["extend_xla_flags", "flag_name", "supported_flags"]

_PROBE = "import jax; jax.numpy.zeros(1).block_until_ready()"
_PROBE_TIMEOUT_S = 300  # generous: JAX's import alone can take tens of seconds on a loaded 2-core machine


def flag_name(flag: str) -> str:
    """``--xla_foo=1`` -> ``xla_foo``."""
    return flag.lstrip("-").split("=", 1)[0]


def supported_flags(flags: Iterable[str]) -> list[str]:
    """The flags of ``flags`` (each ``--name=value``) that this Python's jaxlib accepts, in their order.

    Probed in a subprocess (see the module's docstring), once per distinct list per process.
    """
    return list(_supported(tuple(flags)))


def extend_xla_flags(current: str, flags: Iterable[str]) -> str:
    """``current`` (an ``XLA_FLAGS`` value) with each of ``flags`` that jaxlib knows appended, unless
    ``current`` already sets that flag (an explicit setting wins and is passed on as it is)."""
    present = {flag_name(token) for token in current.split()}
    missing = [flag for flag in flags if flag_name(flag) not in present]
    return " ".join([*current.split(), *supported_flags(missing)])


@functools.cache
def _supported(flags: tuple[str, ...]) -> tuple[str, ...]:
    if not flags:
        return ()
    if _accepted(flags):
        return flags
    if len(flags) == 1:
        return ()
    return tuple(flag for flag in flags if _accepted((flag,)))


def _accepted(flags: tuple[str, ...]) -> bool:
    env = {**os.environ, "XLA_FLAGS": " ".join(flags), "JAX_PLATFORMS": "cpu"}
    try:
        probe = subprocess.run(
            [sys.executable, "-c", _PROBE],
            env=env,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            timeout=_PROBE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        return False
    return probe.returncode == 0
