"""Shared fixtures. Ray: one local instance for the whole session, started only by tests that ask."""

from __future__ import annotations

import os

import pytest

RAY_CPUS = 4  # logical CPUs, pinned so scheduling does not depend on the CI machine (actors use 0.5 each)


def ensure_ray(tmp_path_factory=None):
    # Ray 2.59+ turns token auth on for local clusters; say which mode we want instead of inheriting it.
    os.environ["RAY_AUTH_MODE"] = "disabled"
    import ray

    if not ray.is_initialized():
        if tmp_path_factory is not None and "JAX_COMPILATION_CACHE_DIR" not in os.environ:
            # Worker processes inherit this: every actor compiling the same smoke programs compiles
            # them once per session. A cached executable is the one a fresh compile produces.
            os.environ.update(JAX_COMPILATION_CACHE_DIR=str(tmp_path_factory.mktemp("ray_jax_cache")),
                              JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                              JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")
        # address="local": a fresh instance, never another test process's cluster (pytest-xdist).
        ray.init(address="local", num_cpus=RAY_CPUS, include_dashboard=False, configure_logging=False)
    return ray


@pytest.fixture(scope="session")
def _ray_tmp(tmp_path_factory):
    return tmp_path_factory


@pytest.fixture
def ray_session(_ray_tmp):
    """The session's Ray (re-started if a multi-node test shut it down)."""
    yield ensure_ray(_ray_tmp)


# Files whose tests share nothing and are many: spread test by test over the xdist workers.
_SPREAD_FILES = {"test_conformance.py"}


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name not in _SPREAD_FILES:
            item.add_marker(pytest.mark.xdist_group(item.path.stem))


def pytest_sessionfinish(session, exitstatus):
    import sys

    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()
