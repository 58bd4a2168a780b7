"""Without the ``mcap`` package (a core dependency that an environment set up by hand, such as a GPU machine's
``pip install --no-deps``, may lack): training with the trajectory archive turned off works, and a run that
would archive is refused in one line naming ``pip install mcap`` before anything is written."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import cluster
from cluster.api import archive_settings
from cluster.archive import ArchiveError
from cluster.archive import format as archive_format
from population.config import load_config

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")
# `ocv2 train` in a Python where `import mcap` fails, as it does where mcap is not installed.
WITHOUT_MCAP = "import sys; sys.modules['mcap'] = None; from cluster.cli import main; sys.exit(main(sys.argv[1:]))"


def _train_without_mcap(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", WITHOUT_MCAP, "train", SMOKE, "--backend", "local", "--quiet", *argv],
        cwd=ROOT,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_archive_settings_name_what_each_run_archives():
    sp = load_config(SMOKE)
    assert archive_settings(sp) == ["archive.xp=false"]
    assert archive_settings(sp, evaluate=False) == []  # SP archives only its cross-play
    sa = load_config(SMOKE, ["population.method=sa", "archive.train_every=2", "population.sa.archives=[a.mcap]"])
    assert archive_settings(sa) == [
        "archive.xp=false",
        "archive.sa_collection=false",
        "archive.train_every=0",
        "population.sa.archives=[]",
    ]
    off = ["archive.xp=false", "archive.sa_collection=false", "archive.train_every=0", "population.sa.archives=[]"]
    assert archive_settings(load_config(SMOKE, ["population.method=sa", *off])) == []


def test_a_run_that_archives_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    monkeypatch.setattr(archive_format, "MCAP_AVAILABLE", False)
    with pytest.raises(ArchiveError, match=r"pip install mcap, or turn it off: --set archive.xp=false$"):
        cluster.train_population(SMOKE, tmp_path / "run", backend="local", show_progress=False)
    assert not (tmp_path / "run").exists()


def test_training_without_mcap(tmp_path):
    refused = _train_without_mcap("--out", str(tmp_path / "refused"))
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.strip().splitlines() == [
        "ocv2 train: error: the trajectory archive needs the mcap package: pip install mcap, or turn it off: "
        "--set archive.xp=false"
    ]
    assert not (tmp_path / "refused").exists()

    run = _train_without_mcap("--out", str(tmp_path / "run"), "--set", "archive.xp=false")
    assert run.returncode == 0, run.stderr[-3000:]
    assert (tmp_path / "run" / "xp" / "summary.json").is_file()  # cross-play ran, without its archive
    assert not (tmp_path / "run" / "archive").exists()
