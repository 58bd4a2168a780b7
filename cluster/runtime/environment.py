"""What a run was made with: package versions, the git commit, the devices and the command line.

Every driver that trains into a run directory appends one record to ``RUN_DIR/environment.json``, so a
result can be traced to the code and hardware that produced it (a resumed run has one per driver).
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import platform
import subprocess
import sys
from pathlib import Path

import jax

PACKAGES = ("ocv2", "jax", "jaxlib", "flax", "optax", "numpy", "ray")
_CHECKOUT = Path(__file__).resolve().parents[2]  # the source tree ocv2 is imported from


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages that decide a run's numbers (None: not installed)."""
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def git_state(directory: Path = _CHECKOUT) -> dict | None:
    """``{"commit", "dirty"}`` of the checkout ocv2 runs from; None when it is not a git checkout."""
    if not (directory / ".git").exists():  # e.g. installed into a virtualenv that lives inside another repo
        return None
    try:
        commit = _git(directory, "rev-parse", "HEAD")
        dirty = bool(_git(directory, "status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):  # no git, not a checkout (an installed wheel)
        return None
    return {"commit": commit, "dirty": dirty}


def _git(directory: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(directory), *args], capture_output=True, text=True, timeout=10, check=True)
    return done.stdout.strip()


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
