"""A study's policies for its results: every trained run's checkpoints as published policy files.

    name, added = publish_study("studies/my_study", "docs/results/my_study/policies")

What ``ocv2 study publish`` and study_state/stop_and_pack.py do; the files and their SHA256SUMS.json are
``population.published``'s. The runs are the study directory's ``runs/<name>/`` that hold a config.
"""

from __future__ import annotations

from pathlib import Path

from cluster.runtime.rundir import enclosing_run
from cluster.study.runner import read_state
from cluster.study.spec import StudyError
from population.published import PublishedPolicy, publish_runs


def trained_runs(study) -> tuple[str, list[Path]]:
    """The study's name and its run directories, or a ``StudyError`` naming what is missing."""
    study = Path(study)
    state = read_state(study)
    if state is None:
        raise StudyError(f"{study}: no study.json here (not a study directory: see `ocv2 study run --out`)")
    runs = sorted(config.parent for config in (study / "runs").glob("*/config.yaml"))
    if not runs:
        raise StudyError(f"{study}: no trained run under runs/ (run `ocv2 study run` first)")
    return state.study, runs


def publish_study(study, out, which: str = "snapshots") -> tuple[str, dict[str, list[PublishedPolicy]]]:
    """Publish every run's checkpoints that ``which`` selects into ``out``, all runs or none
    (``population.published.publish_runs``); returns the study's name and, per run, the entries added."""
    name, runs = trained_runs(study)
    where = Path(out).resolve()
    if where.is_relative_to(Path(study).resolve()):
        raise StudyError(f"--out {out}: lies inside the study directory {study}; give a folder outside it")
    run = enclosing_run(where / "policy")
    if run is not None:  # policy files beside a run's config.yaml and checkpoints, as `ocv2 export` refuses
        raise StudyError(f"--out {out}: lies inside the run directory {run}; give a folder outside it")
    return name, publish_runs(runs, out, which)
