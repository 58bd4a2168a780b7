"""What a wheel ships and what a fresh clone's README commands leave behind (the wheel itself is built,
installed outside the checkout and exercised by .ci/run with .ci/wheel_check.py)."""

from __future__ import annotations

import fnmatch
import re
import subprocess
import tomllib
from pathlib import Path

import pytest

from population.config import PACKAGED_CONFIGS

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_config_is_package_data():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"][
        "population.config"
    ]
    files = Path(str(PACKAGED_CONFIGS))
    shipped = [p.relative_to(files.parent).as_posix() for p in files.rglob("*") if p.is_file()]
    assert len(shipped) > 40
    missed = [name for name in shipped if not any(fnmatch.fnmatch(name, pattern) for pattern in patterns)]
    assert not missed, f"not in the wheel: {missed}"


def test_configs_in_a_checkout_are_the_packaged_ones():
    assert (ROOT / "configs").resolve() == Path(str(PACKAGED_CONFIGS)).resolve()


def test_quickstart_header_gives_the_readme_install_command():
    readme = (ROOT / "README.md").read_text()
    command = re.search(r"^(pip install -e \S+ && ocv2 train configs/quickstart\.yaml)$", readme, re.M)
    assert command, "the README's main job is missing"
    header = [line for line in (ROOT / "configs" / "quickstart.yaml").read_text().splitlines() if line.startswith("#")]
    assert any(command.group(1) in line for line in header)
    assert not any(re.search(r"pip install -e \.(\s|$)", line) for line in header)  # the core alone has no Ray


@pytest.mark.parametrize(
    "path",
    [
        ".venv/bin/python",
        "runs/smoke/metrics.csv",
        "data/overcooked_ai-1.1.0.tar.gz",
        "cook.ocv2policy",
        "runs/sa/seed_3.ocv2policy",
        "reports/report.md",
        "dist/ocv2-0.1.0-py3-none-any.whl",
        "build/lib/ocv2/env.py",
        "ocv2.egg-info/PKG-INFO",
    ],
)
def test_what_the_readme_commands_create_is_ignored(path):
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    assert subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT).returncode == 0, path
