"""How training computes its numbers: matmul precision (``run.precision``) and XLA's deterministic GPU
operations (``run.deterministic``).

**Precision.** JAX's default precision for float32 matmuls and convolutions is the backend's choice: float32
on a CPU, but TF32 (inputs rounded to a 10-bit mantissa) on NVIDIA GPUs since Ampere (A100, H100). A run
says which it wants instead: ``run.precision`` is ``float32`` (the default), ``tf32`` or ``bf16``, mapped to
``jax.default_matmul_precision("float32" | "tensorfloat32" | "bfloat16")`` and entered with
:func:`matmul_precision` wherever training, SA collection, cross-play and GIFs are traced. JAX's jit cache
is keyed by that setting, so a program traced under one precision is never reused under another. What each
computes, as ``jax.lax.Precision`` documents it: ``float32`` is HIGHEST (float32 everywhere); ``tf32`` is
HIGH (TF32 on an NVIDIA GPU, 3 bfloat16 passes on a TPU); ``bf16`` is DEFAULT (one bfloat16 pass on a TPU,
but TF32 again on an NVIDIA GPU). On a CPU the three compute the same float32 numbers (XLA:CPU ignores the
setting; checked bit for bit with jaxlib 0.10.2).

**Determinism.** XLA's GPU scatter-adds and some reductions use atomics whose order varies from run to run;
``--xla_gpu_deterministic_ops=true`` makes XLA pick deterministic implementations (slower) or refuse to
compile an op that has none. XLA reads ``XLA_FLAGS`` once, when JAX starts its first backend, so the flag
has to be in the environment before that: :func:`enable_deterministic_ops` for this process, and the Ray
backend's ``actor_env`` for its actors. The flag is added only where the running jaxlib knows it
(``population.xla_flags``): XLA ends the process on a flag it does not know. It changes nothing on a CPU
(XLA:CPU is deterministic already).

JAX is imported only inside the functions that need it; :func:`enable_deterministic_ops` only needs JAX's
backend not to have started yet.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator, MutableMapping

from population.config.schema import PRECISIONS, RunConfig
from population.xla_flags import extend_xla_flags, flag_name, supported_flags

#: ``run.precision``'s default: also what a policy is played at where nothing says how it trained.
DEFAULT_PRECISION = RunConfig().precision
#: ``run.precision`` -> the name ``jax.default_matmul_precision`` takes.
_JAX_NAMES = {"float32": "float32", "tf32": "tensorfloat32", "bf16": "bfloat16"}
assert tuple(_JAX_NAMES) == PRECISIONS
#: Relative tolerance (of an array's own scale) to which two arrangements of the same matmuls agree under
#: each precision: float32 rounding of differently ordered sums; TF32's 10-bit and bfloat16's 7-bit mantissas.
_RELATIVE_TOLERANCE = {"float32": 1e-5, "tf32": 1e-3, "bf16": 1e-2}
DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def jax_precision(precision: str) -> str:
    """``run.precision`` -> the value of ``jax.default_matmul_precision``."""
    try:
        return _JAX_NAMES[precision]
    except KeyError:
        raise ValueError(f"run.precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}") from None


@contextlib.contextmanager
def matmul_precision(precision: str) -> Iterator[None]:
    """Trace (and so compile) the JAX code inside with ``precision``'s matmul/convolution precision."""
    import jax

    with jax.default_matmul_precision(jax_precision(precision)):
        yield


def set_process_precision(precision: str) -> None:
    """Make ``precision`` this process's default (a Ray actor, which serves one run's shard and nothing else)."""
    import jax

    jax.config.update("jax_default_matmul_precision", jax_precision(precision))


def precision_in_force() -> str:
    """The ``run.precision`` name of what float32 matmuls compute here and now, under the precision set by
    :func:`matmul_precision` or the process default. As ``jax.lax.Precision`` documents it: a CPU computes
    float32 whatever the setting; an NVIDIA GPU computes float32 at ``float32`` (HIGHEST) and TF32 otherwise
    (since Ampere: JAX's ``bfloat16`` is DEFAULT, which XLA:GPU computes in TF32, as it does HIGH); a TPU
    computes one bfloat16 pass at DEFAULT."""
    import jax

    backend = jax.default_backend()
    setting = str(jax.config.jax_default_matmul_precision or "default").lower()
    if backend == "cpu" or setting in ("highest", "float32"):
        return "float32"
    if backend == "tpu" and setting in ("default", "fastest", "bfloat16"):
        return "bf16"
    return "tf32"


def relative_tolerance(precision: str | None = None) -> float:
    """How closely two computations of the same matmuls agree, relative to the arrays' scale, under
    ``precision`` (default: the precision in force)."""
    return _RELATIVE_TOLERANCE[precision or precision_in_force()]


# ---------------------------------------------------------------------------------------------------
# XLA's deterministic GPU ops
# ---------------------------------------------------------------------------------------------------


def deterministic_ops_in(xla_flags: str) -> bool:
    """Whether an ``XLA_FLAGS`` value turns XLA's deterministic GPU ops on (the last setting wins)."""
    value = None
    for token in xla_flags.split():
        if flag_name(token) == flag_name(DETERMINISTIC_FLAG):
            value = token.split("=", 1)[1].lower() if "=" in token else "true"
    return value in ("true", "1")


def deterministic_flag_known() -> bool:
    """Whether the running jaxlib knows ``--xla_gpu_deterministic_ops`` (probed once per process)."""
    return bool(supported_flags([DETERMINISTIC_FLAG]))


def with_deterministic_ops(xla_flags: str) -> str:
    """``xla_flags`` plus ``--xla_gpu_deterministic_ops=true`` if the running jaxlib knows it (an explicit
    setting of the flag in ``xla_flags`` wins)."""
    return extend_xla_flags(xla_flags, [DETERMINISTIC_FLAG])


def jax_backend_started() -> bool:
    """Whether JAX has started a backend in this process (it has read XLA_FLAGS then, once and for all)."""
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    started = getattr(xla_bridge, "backends_are_initialized", None)
    return started() if started is not None else bool(getattr(xla_bridge, "_backends", None))


def enable_deterministic_ops(environ: MutableMapping[str, str] | None = None) -> tuple[bool, str]:
    """Put ``--xla_gpu_deterministic_ops=true`` into this process's ``XLA_FLAGS`` before JAX starts a backend.

    Returns (whether the flag is in force for this process, a sentence saying what happened). Once JAX has
    started a backend it has read ``XLA_FLAGS`` for good: then nothing is changed (a later subprocess or
    Ray actor would inherit a flag this process does not have) and the sentence says so.
    """
    environ = os.environ if environ is None else environ
    current = environ.get("XLA_FLAGS", "")
    if deterministic_ops_in(current):
        return True, "XLA's deterministic GPU ops are on (XLA_FLAGS sets --xla_gpu_deterministic_ops)"
    if flag_name(DETERMINISTIC_FLAG) in {flag_name(token) for token in current.split()}:
        return False, "run.deterministic: XLA_FLAGS turns --xla_gpu_deterministic_ops off explicitly; left as it is"
    if jax_backend_started():
        return False, (
            "run.deterministic: JAX was already running in this process when the run started, and XLA reads "
            "XLA_FLAGS only once, so --xla_gpu_deterministic_ops is not in force here (it matters on a GPU only; "
            "set XLA_FLAGS=--xla_gpu_deterministic_ops=true before starting Python to have it)"
        )
    flags = with_deterministic_ops(current)
    if not deterministic_ops_in(flags):
        return False, "run.deterministic: this jaxlib does not know --xla_gpu_deterministic_ops; not set"
    environ["XLA_FLAGS"] = flags
    return True, "XLA's deterministic GPU ops are on (--xla_gpu_deterministic_ops=true added to XLA_FLAGS)"
