"""What a run was made with: package versions, the git commit, the devices and the command line.

Every driver that trains into a run directory appends one record to ``RUN_DIR/environment.json``, so a
result can be traced to the code and hardware that produced it (a resumed run has one per driver). Once
its workers have started, the record gets one ``process_record`` per worker (the device it trains on, its
matmul precision and XLA flags) and the run's ``run.precision`` and ``run.deterministic``.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import os
import platform
import subprocess
import sys
from pathlib import Path

import jax

from population.numerics import deterministic_ops_in, precision_in_force

PACKAGES = ("ocv2", "jax", "jaxlib", "flax", "optax", "numpy", "ray")
_CHECKOUT = Path(__file__).resolve().parents[2]  # the source tree ocv2 is imported from


def package_versions(extra: tuple[str, ...] = ()) -> dict[str, str | None]:
    """Installed versions of the packages that decide a run's numbers, and of ``extra`` (None: not installed)."""
    versions = {"python": platform.python_version()}
    for name in (*PACKAGES, *extra):
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


#: At most this many changed files are named in ``git_state``'s ``changed`` (the count is always there).
CHANGED_NAMED = 50


def git_state(directory: Path = _CHECKOUT) -> dict | None:
    """``{"commit", "dirty", "changed", "changed_count"}`` of the checkout ocv2 runs from; None when it is not a git
    checkout. ``changed``: the tracked files that differ from the commit (the first ``CHANGED_NAMED``, sorted), so
    that a reader can tell a run made beside edited docs or tests from one made with edited training code."""
    if not (directory / ".git").exists():  # e.g. installed into a virtualenv that lives inside another repo
        return None
    try:
        commit = _git(directory, "rev-parse", "HEAD")
        # -z: names as they are (no quoting of odd characters); staged and unstaged changes alike
        status = _git(directory, "status", "--porcelain", "-z", "--untracked-files=no", strip=False)
    except (OSError, subprocess.SubprocessError):  # no git, not a checkout (an installed wheel)
        return None
    changed = sorted(_changed_paths(status))
    return {"commit": commit, "dirty": bool(changed), "changed": changed[:CHANGED_NAMED], "changed_count": len(changed)}


def _changed_paths(status: str) -> list[str]:
    """The paths ``git status --porcelain -z`` names: ``XY path``, a rename's or copy's old path as an entry of its
    own after it (skipped: the new name is the file there now)."""
    entries, paths = status.split("\0"), []
    i = 0
    while i < len(entries):
        entry = entries[i]
        i += 1
        if len(entry) < 4:
            continue
        paths.append(entry[3:])
        if "R" in entry[:2] or "C" in entry[:2]:  # the old name follows (a rename staged, or only in the work tree)
            i += 1
    return paths


def _git(directory: Path, *args: str, strip: bool = True) -> str:
    # backslashreplace: a file name that is not UTF-8 (-z leaves it unquoted) is named with escapes, not an error
    done = subprocess.run(
        ["git", "-C", str(directory), *args],
        capture_output=True,
        text=True,
        errors="backslashreplace",
        timeout=10,
        check=True,
    )
    return done.stdout.strip() if strip else done.stdout  # porcelain lines start with a status that may be a space


def environment_record() -> dict:
    """This process: versions, git commit (or None), JAX devices, argv and the time."""
    return {
        "time": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "versions": package_versions(),
        "git": git_state(),
        "argv": list(sys.argv),
        "devices": [str(device) for device in jax.devices()],
        "platform": platform.platform(),
    }


#: The CPU features XLA:CPU's kernels use when they are there: a training rate measured on one CPU says little of
#: another without them (2026-11-30: the same resumed SA run trained at 505 s per 5 updates on one 2-core machine,
#: about three times as long on the next).
VECTOR_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_tile", "asimd", "sve")


def cpu_record(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict:
    """The CPU this process runs on: its model (``/proc/cpuinfo``'s first "model name", else what ``platform``
    says), the cores there are and the cores this process may use, and which of ``VECTOR_FLAGS`` it has (None where
    ``cpuinfo`` cannot be read: not Linux)."""
    model, flags = None, None
    try:
        text = cpuinfo.read_text()
    except OSError:
        text = None
    if text is not None:
        fields = {}
        for line in text.splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())  # the first processor's
        model = fields.get("model name")
        present = set(fields.get("flags", fields.get("Features", "")).split())
        flags = [flag for flag in VECTOR_FLAGS if flag in present]
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {
        "model": model or platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "vector_flags": flags,
    }


def describe_devices(devices=None) -> str:
    """What JAX computes on, in words: ``cpu``, ``gpu: NVIDIA H100 80GB HBM3`` or ``gpu: 2 x NVIDIA H100 ...``
    (the platform, and the device kind unless it is the CPU)."""
    devices = jax.devices() if devices is None else devices
    kinds: dict[str, int] = {}
    for device in devices:
        name = "cpu" if device.platform == "cpu" else f"{device.platform}: {device.device_kind}"
        kinds[name] = kinds.get(name, 0) + 1
    return ", ".join(name if count == 1 else name.replace(": ", f": {count} x ", 1) for name, count in kinds.items())


def process_record() -> dict:
    """This process as a worker: its CPU (``cpu_record``), the device JAX trains on, the matmul precision and XLA flags in force
    (``jax.default_matmul_precision`` here and now; None is the backend's default), and the variables that
    decide which devices it sees."""
    xla_flags = os.environ.get("XLA_FLAGS", "")
    return {
        "pid": os.getpid(),
        "cpu": cpu_record(),
        "device": describe_devices(),
        "devices": [str(device) for device in jax.devices()],
        "matmul_precision": jax.config.jax_default_matmul_precision,
        "computes": precision_in_force(),
        "xla_gpu_deterministic_ops": deterministic_ops_in(xla_flags),
        "xla_flags": xla_flags,
        "jax_platforms": os.environ.get("JAX_PLATFORMS"),
        "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"),
    }
