"""Shared fixtures. Fast compiles and one JAX compilation cache for the whole session; one local Ray
instance per process, started only by tests that ask."""

from __future__ import annotations

import gc
import os
import shutil
import sys
import tempfile

import pytest

from population.xla_flags import extend_xla_flags

RAY_CPUS = 4  # logical CPUs, pinned so scheduling does not depend on the CI machine (actors use 0.5 each)

# Compilation dominates the training, cross-play and Ray tests, and many of them build the same
# programs (the smoke run, its resume, its rerun; every Ray actor). JAX's persistent cache keys an
# executable by the program it compiles, so a hit returns what a fresh compile would: no result
# depends on the cache. One directory serves the pytest-xdist workers and the Ray actors they start
# (both inherit the environment); a size cap turns on JAX's file lock, which makes that sharing safe.
# JAX options; each is also read from the environment variable of the same name in upper case.
_CACHE_OPTIONS = {
    "jax_persistent_cache_min_compile_time_secs": 0.1,  # skip the tiny op-by-op programs
    "jax_persistent_cache_min_entry_size_bytes": -1,
    "jax_compilation_cache_max_size": 8 << 30,
}


# XLA flags for the tests. Each is set only where the running jaxlib knows it (population/xla_flags.py probes
# that in a subprocess): XLA ends the whole process at an unknown flag in XLA_FLAGS, before any test can
# report, and flags come and go between jaxlib releases. An explicit setting in XLA_FLAGS wins over each.
_TEST_XLA_FLAGS = [
    # LLVM optimisation off: compiling is most of the suite's time and the programs it runs are tiny (9.5
    # instead of 13.5 minutes for the whole suite on 2 cores). XLA keeps its HLO passes (fusion) and fast-math
    # stays off, so values agree with optimised code up to float rounding (a smoke RNN run's metrics: to 1e-6
    # absolute), and no test compares with numbers stored from another build.
    # XLA_FLAGS=--xla_backend_optimization_level=2 tests the optimised code.
    "--xla_backend_optimization_level=0",
    # XLA's classic CPU fusion emitters instead of its newer MLIR ones: a conformance rollout compiles in 7 s
    # of CPU instead of 11 s, and the whole suite took 14 instead of 17 minutes on 2 cores (jaxlib 0.10.2).
    # Values again agree to float rounding (the same smoke run: to 1e-5 relative). jaxlib 0.11.2 no longer
    # knows the flag (the MLIR emitters are the only ones), so there it is left out.
    "--xla_cpu_use_fusion_emitters=false",
    # What `ocv2 train` and `ocv2 study run` set for themselves (run.deterministic) when JAX has not started: set
    # for the whole session, so a command called in a test process where JAX already runs finds it in force
    # and logs nothing about it (a stray log line broke one-line-error tests, depending on test order). No
    # effect on a CPU; tests/test_numerics.py takes it out to test the message.
    "--xla_gpu_deterministic_ops=true",
]


# Ray starts idle Python workers ahead of time (as many as the node's CPUs) for tasks; ocv2 runs only
# actors, which get workers of their own (their runtime env differs), so those idle ones only cost
# start-up CPU at every Ray start of the session.
_RAY_NO_PRESTART = {"RAY_prestart_worker_first_driver": "0", "RAY_enable_worker_prestart": "0"}


def pytest_configure(config):
    if hasattr(config, "workerinput"):
        return  # an xdist worker: it inherits the controller's environment
    for name, value in _RAY_NO_PRESTART.items():
        os.environ.setdefault(name, value)
    # Before JAX starts a backend here; xdist workers, Ray actors and subprocesses inherit the result.
    os.environ["XLA_FLAGS"] = extend_xla_flags(os.environ.get("XLA_FLAGS", ""), _TEST_XLA_FLAGS)
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return  # the caller chose a cache
    config._ocv2_jax_cache = tempfile.mkdtemp(prefix="ocv2-tests-jax-cache-")
    options = {**_CACHE_OPTIONS, "jax_compilation_cache_dir": config._ocv2_jax_cache}
    os.environ.update({name.upper(): str(value) for name, value in options.items()})
    if "jax" in sys.modules:  # imported before this hook (by a plugin): JAX read its env already
        import jax

        for name, value in options.items():
            jax.config.update(name, value)


def pytest_unconfigure(config):
    cache = getattr(config, "_ocv2_jax_cache", None)
    if cache is not None:
        shutil.rmtree(cache, ignore_errors=True)


def ensure_ray():
    # Ray is an extra (ocv2[ray], in the test extra): an environment without it, such as CI's second leg
    # (a GPU machine's packages), skips the tests that need it.
    pytest.importorskip("ray", reason="needs Ray (pip install 'ocv2[ray]')")
    # Ray 2.59+ turns token auth on for local clusters; say which mode we want instead of inheriting it.
    os.environ["RAY_AUTH_MODE"] = "disabled"
    import ray

    from cluster.runtime.ray_backend import start_local

    if not ray.is_initialized():
        # Actors inherit the environment, so they share the session's compilation cache (above).
        # A fresh instance, never another test process's cluster (pytest-xdist), started as ocv2 starts
        # one (without the fork warnings JAX would print, as it is already running here).
        start_local(num_cpus=RAY_CPUS)
    return ray


@pytest.fixture
def ray_session():
    """The session's Ray (re-started if a multi-node test shut it down)."""
    yield ensure_ray()


@pytest.fixture
def fresh_programs():
    """No cached trainer or training program (population.ppo keeps them per config for the process): for a
    test that counts traces or swaps a function the programs call, which a program an earlier test of the
    same worker built would skip."""
    from population import ppo

    ppo.clear_program_caches()
    yield
    ppo.clear_program_caches()  # nor one built with the swapped function for the tests after


# Files whose tests share nothing and are many: spread test by test over the xdist workers.
_SPREAD_FILES = {"test_conformance.py"}


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name not in _SPREAD_FILES:
            item.add_marker(pytest.mark.xdist_group(item.path.stem))
    # xdist hands out work in this order (pyproject: --no-loadscope-reorder): the whole files first,
    # then the spread tests, which fill the workers' gaps at the end instead of leaving one idle
    # while the other finishes a long file.
    items.sort(key=lambda item: item.path.name in _SPREAD_FILES)


@pytest.hookimpl(trylast=True)  # after the session's own teardown (with -x it runs late), still before xdist's report
def pytest_sessionfinish(session, exitstatus):
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()
    if hasattr(session.config, "workerinput"):
        settle_heap()


def settle_heap() -> None:
    """Collect once, then freeze what is left, so that an xdist worker's last steps stay short.

    After a worker reports its session finished, execnet gives it 5 s to end and then sends it a SIGINT. In those
    seconds pytest runs 5 full garbage collections (to surface exceptions raised in ``__del__``), each with JAX's gc
    callback, over a heap of compiled programs: 6.6 s for a worker's 790,000 objects here, and the SIGINT surfaced as
    a KeyboardInterrupt "ignored in _xla_gc_callback" at the end of the suite. This runs before the report (inside
    xdist's own sessionfinish), collects the garbage the tests left (its ``__del__`` errors still reach pytest), and
    freezes the survivors, which the later collections then skip."""
    gc.collect()
    gc.freeze()
