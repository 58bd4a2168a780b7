"""The README's Python snippets run as pasted: every ```python block, in order, in one fresh interpreter.

They run in an empty folder holding the repository's ``configs/`` (as in a checkout), so the training
snippet's ``runs/smoke`` is the run the later policy snippet loads. configs/smoke.yaml keeps that to one
small compile.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```$", markdown, flags=re.S | re.M)


def test_the_readme_has_python_snippets_and_they_are_found():
    blocks = python_blocks((ROOT / "README.md").read_text())
    assert len(blocks) >= 3 and all(block.strip() for block in blocks)
    assert python_blocks("text\n```python\nx = 1\n```\n```bash\nls\n```\n") == ["x = 1\n"]


def test_every_readme_python_snippet_runs_as_pasted(tmp_path):
    blocks = python_blocks((ROOT / "README.md").read_text())
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    script = "\n".join(f"print('--- README snippet {i}', flush=True)\n{block}" for i, block in enumerate(blocks))
    (tmp_path / "readme_snippets.py").write_text(script)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    done = subprocess.run(
        [sys.executable, "readme_snippets.py"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert f"--- README snippet {len(blocks) - 1}" in done.stdout


def test_ci_runs_the_readme_test_command_lint_first_and_without_q():
    """.ci/run runs what the README tells people to run. No -q: at negative verbosity pytest-xdist prints
    "bringing up nodes..." twice on a non-terminal."""
    readme = (ROOT / "README.md").read_text()
    (command,) = [line for line in readme.splitlines() if line.startswith('pip install -e ".[test]" && ')]
    steps = command.split(" && ")[1:]
    assert steps == ["ruff check .", "ruff format --check .", "python -m pytest"]
    ci = [
        line.strip()
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    # each its own line: under set -e a failure on the left of `&&` would not stop the script
    assert "ruff check ." in ci and "ruff format --check ." in ci and "python -m pytest" in ci
    assert ci.index("ruff check .") < ci.index("ruff format --check .") < ci.index("python -m pytest")
    assert not any("&&" in line and "ruff" in line for line in ci)
    # After it comes only the second leg (Python 3.12 without Ray and mcap), in a virtual environment of its
    # own: nothing more runs in the environment the README's commands made.
    second_leg = ci[ci.index("python -m pytest") + 1 :]
    assert second_leg and not any(line.startswith(("python ", "pip ", "ruff ")) for line in second_leg)
