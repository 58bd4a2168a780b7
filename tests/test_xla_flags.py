"""population/xla_flags.py: only flags the running jaxlib knows reach XLA_FLAGS (XLA ends the process at an
unknown one)."""

from __future__ import annotations

import os
import subprocess
import sys

from population.xla_flags import extend_xla_flags, flag_name, supported_flags

KNOWN = "--xla_backend_optimization_level=0"  # in every jaxlib ocv2 supports
UNKNOWN = "--xla_ocv2_no_such_flag=true"


def test_unknown_flags_are_dropped_known_ones_kept():
    assert supported_flags([KNOWN, UNKNOWN]) == [KNOWN]
    assert supported_flags([UNKNOWN]) == []
    assert supported_flags([]) == []


def test_an_explicit_setting_wins_and_is_not_probed():
    # Not even probed: an unknown flag already in XLA_FLAGS is the caller's choice and is passed on.
    assert extend_xla_flags(f"--xla_backend_optimization_level=2 {UNKNOWN}", [KNOWN]) == (
        f"--xla_backend_optimization_level=2 {UNKNOWN}"
    )
    assert extend_xla_flags("", [UNKNOWN, KNOWN]) == KNOWN
    assert flag_name("--xla_gpu_deterministic_ops=true") == "xla_gpu_deterministic_ops"


def test_the_sessions_flags_start_jax():
    # tests/conftest.py set XLA_FLAGS from the probe; a subprocess inheriting it (as Ray actors do) runs JAX.
    run = subprocess.run(
        [sys.executable, "-c", "import jax; print(jax.numpy.ones(2).sum())"],
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "xla_backend_optimization_level" in os.environ["XLA_FLAGS"]  # set by conftest (or by the caller)
