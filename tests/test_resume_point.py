"""Where a resume starts (``cluster.runtime.runstate.resume_updates``): the newest update every seed of a shard
has. Checkpoints are saved one seed at a time, so a kill, a full disk or a stopped Ray actor can leave some seeds
one stop ahead; seeds that share no update at all (a copy or pack missing files) are refused, never started over.

Every run is configs/smoke.yaml (2 seeds x 4 updates, snapshots at 0, 2 and 4) on the local backend.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cluster.cli import main
from cluster.runtime import coordinator, runstate
from cluster.runtime.interrupt import StoppedAfterChunk
from cluster.runtime.local import LocalWorkers
from cluster.runtime.rundir import RunDir
from population import checkpoints as ckpt

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")
NUM_SEEDS, NUM_UPDATES = 2, 4
TIMING_COLUMNS = {"steps_per_s", "wall_s"}


def train(out, *extra) -> int:
    return main(["train", SMOKE, "--out", str(out), "--quiet", "--backend", "local", "--no-eval", *extra])


@pytest.fixture(scope="module")
def sp_run(tmp_path_factory):
    """One uninterrupted SP run (shared, never modified: tests copy it)."""
    out = tmp_path_factory.mktemp("runs") / "sp"
    assert train(out) == 0
    return out


def _stopped_after_update_2(sp_run, run) -> None:
    """A copy of ``sp_run`` as its driver left it when killed once update 2 was merged."""
    shutil.copytree(sp_run, run)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(run, seed, NUM_UPDATES).unlink()
    RunDir(run).update_manifest(status="training", update=2)
    lines = (run / "metrics.csv").read_text().splitlines(keepends=True)
    update_column = lines[0].rstrip("\r\n").split(",").index("update")
    kept = [line for line in lines[1:] if int(float(line.split(",")[update_column])) <= 2]
    (run / "metrics.csv").write_text("".join([lines[0], *kept]))  # the rows of update 3-4 were never merged


def _metrics(run) -> list[dict]:
    with open(Path(run) / "metrics.csv", newline="") as handle:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(handle)]


def _assert_same_run(run, reference) -> None:
    for seed in range(NUM_SEEDS):
        ours, theirs = (ckpt.read(ckpt.checkpoint_path(r, seed, NUM_UPDATES))[1] for r in (run, reference))
        for a, b in zip(_leaves(ours), _leaves(theirs), strict=True):
            np.testing.assert_array_equal(a, b)
    assert _metrics(run) == _metrics(reference)


def _leaves(tree):
    if isinstance(tree, dict):
        return [leaf for key in sorted(tree) for leaf in _leaves(tree[key])]
    return [np.asarray(tree)]


def test_a_save_cut_short_after_some_seeds_resumes_from_the_update_they_all_have(sp_run, tmp_path, capsys):
    """A kill (or a full disk) after seed 0's update-4 file leaves seed 1 at update 2, which both still have. The
    resume starts there, says so, and trains updates 3-4 again to the same numbers."""
    run = tmp_path / "cut_save"
    _stopped_after_update_2(sp_run, run)
    shutil.copy(ckpt.checkpoint_path(sp_run, 0, NUM_UPDATES), ckpt.checkpoint_path(run, 0, NUM_UPDATES))
    assert train(run, "--resume") == 0
    assert json.loads((run / "manifest.json").read_text())["resumed_from"] == 2
    assert "seed 0 at 4, but update 2 is the newest every seed of [0, 1] has" in capsys.readouterr().err
    _assert_same_run(run, sp_run)


def test_a_resume_of_seeds_that_share_no_update_is_refused_and_nothing_is_lost(sp_run, tmp_path, capsys):
    """Seed 0 at update 4 only and seed 1 at update 2 only (a pack that kept each seed's newest file) once resumed
    from update 0: seed 1's update 2 pruned and metrics.csv cut to nothing, without a word."""
    run = tmp_path / "no_common"
    shutil.copytree(sp_run, run)
    for seed, kept in ((0, 4), (1, 2)):
        for update in ckpt.list_updates(run, seed):
            if update != kept:
                ckpt.checkpoint_path(run, seed, update).unlink()

    def kept_files() -> dict:
        return {p: p.read_bytes() for p in [run / "metrics.csv", *(run / "checkpoints").rglob("*")] if p.is_file()}

    before = kept_files()
    assert train(run, "--resume") == 2
    err = capsys.readouterr().err
    assert f"{run / 'checkpoints'}: the seeds share no checkpoint update (seed 0: 4; seed 1: 2)" in err, err
    assert "nothing was trained or deleted" in err
    assert kept_files() == before


@pytest.mark.parametrize(
    "found, expected",
    [
        ({0: [], 1: []}, []),  # nothing saved yet
        ({0: [0], 1: []}, []),  # stopped while saving update 0: starting again loses nothing
        ({0: [0, 2, 4], 1: [0, 2]}, [2, 0]),  # a save of update 4 cut short after seed 0
        ({0: [4], 1: [2]}, "seed 0: 4; seed 1: 2"),
        ({0: [2], 1: []}, "seed 0: 2; seed 1: none"),
    ],
)
def test_resume_updates_are_those_every_seed_has_or_an_error_naming_each_seed(tmp_path, found, expected):
    for seed, updates in found.items():
        ckpt.seed_dir(tmp_path, seed).mkdir(parents=True)
        for update in updates:
            ckpt.checkpoint_path(tmp_path, seed, update).write_bytes(b"")
    if isinstance(expected, list):
        assert runstate.resume_updates(tmp_path, list(found)) == expected
    else:
        with pytest.raises(ckpt.CheckpointError, match=f"share no checkpoint update \\({expected}\\)"):
            runstate.resume_updates(tmp_path, list(found))


class _SignalDuringCatchUp(LocalWorkers):
    """Local workers whose first ``advance`` (a resume's catch-up pass) reports a Ctrl-C or SIGTERM, as
    ``ChunkWait`` does when one lands while the chunk runs."""

    def call(self, method, jobs):
        results = super().call(method, jobs)
        if method == "advance" and not getattr(self, "signalled", False):
            self.signalled = True
            results = [result._replace(stop_requested=True) for result in results]
        return results


def test_a_signal_during_the_catch_up_pass_stops_once_its_rows_are_recorded(sp_run, tmp_path):
    """A resume whose metrics.csv lacks the last chunk's rows first catches them up from the checkpoints; a signal
    then was said ("... so it is saved, then stopping") and ignored: training went on to the end."""
    run = tmp_path / "catch_up"
    shutil.copytree(sp_run, run)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(run, seed, NUM_UPDATES).unlink()
    RunDir(run).update_manifest(status="training", update=2)
    header = (run / "metrics.csv").read_text().splitlines(keepends=True)[0]
    (run / "metrics.csv").write_text(header)  # updates 1-2 never merged: the catch-up takes them from update 2
    config = RunDir(run).load_config()
    with pytest.raises(StoppedAfterChunk):
        coordinator.train(config, run, _SignalDuringCatchUp, resume=True, show_progress=False, evaluate=False)
    assert sorted({int(row["update"]) for row in _metrics(run)}) == [1, 2]  # the caught-up rows are recorded
    assert ckpt.list_updates(run, 0) == [0, 2]  # and nothing was trained past them
