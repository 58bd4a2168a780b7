"""Extending a truncated run (``ocv2 train --resume --extend``, ``cluster.runtime.extend``): the run trained
on along its schedule is the run trained to the later stop at once, bit for bit; what cannot be an
extension is refused by name and leaves the run as it was.

Runs are configs/smoke.yaml on a 6-update schedule: stopped after 3 updates, then extended to 6.
"""

from __future__ import annotations

import json
import shutil

import pytest
from test_train_cli import (
    NUM_SEEDS,
    SMOKE,
    _assert_same_metrics,
    _assert_trees_equal,
    _raw_checkpoint,
    manifest,
    read_csv,
    train,
)

from cluster.cli import main
from cluster.runtime.extend import extend_run, sealed_files
from cluster.runtime.rundir import RunDir, RunDirError
from population import checkpoints as ckpt
from population import policy, published
from population.config import load_config

SCHEDULE = "ppo.schedule_timesteps=768"  # 6 updates of 128 env steps
FIRST, LATER = "ppo.total_timesteps=384", "ppo.total_timesteps=768"  # stops after 3 and after 6 updates


@pytest.fixture(scope="module")
def truncated(tmp_path_factory):
    """A run stopped after 3 of its schedule's 6 updates, evaluated (shared, never modified: tests copy it)."""
    out = tmp_path_factory.mktemp("extend") / "truncated"
    assert train(out, SCHEDULE, FIRST, "eval.episodes=3") == 0
    return out


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The same schedule trained to update 6 at once."""
    out = tmp_path_factory.mktemp("extend") / "straight"
    assert train(out, SCHEDULE, LATER, extra=["--no-eval"]) == 0
    return out


def test_an_extended_run_is_the_run_trained_to_the_later_stop(truncated, straight, tmp_path):
    run = tmp_path / "extended"
    shutil.copytree(truncated, run)
    assert train(run, SCHEDULE, LATER, extra=["--resume", "--extend", "--no-eval"]) == 0
    for seed in range(NUM_SEEDS):  # whole TrainStates, bit for bit
        for update in (3, 6):
            _assert_trees_equal(_raw_checkpoint(run, seed, update), _raw_checkpoint(straight, seed, update))
    _assert_same_metrics(read_csv(run / "metrics.csv"), read_csv(straight / "metrics.csv"))
    # The first stop's snapshots stay (its update 2 is none of the longer run's 0, 3, 6) ...
    assert all(ckpt.list_updates(run, seed) == [0, 2, 3, 6] for seed in range(NUM_SEEDS))
    assert all(ckpt.list_updates(straight, seed) == [0, 3, 6] for seed in range(NUM_SEEDS))
    assert published.updates_to_publish(run, 0) == [2, 3, 6]  # `ocv2 study publish` exports them too
    # ... and so does the evaluation made there; the manifest says what happened.
    kept = run / "extended" / "update_0000003"
    assert json.loads((kept / "xp" / "summary.json").read_text()) == json.loads(
        (truncated / "xp" / "summary.json").read_text()
    )
    assert not (run / "xp").exists()
    assert sorted(p.name for p in (kept / "archive" / "xp").iterdir()) == sorted(
        p.name for p in (truncated / "archive" / "xp").iterdir()
    )  # the old stop's cross-play episodes: the new evaluation writes the same file names
    assert load_config(run / "config.yaml").eval.episodes == 3  # keys outside the fingerprint stay the run's
    (record,) = manifest(run)["extensions"]
    assert (record["from_updates"], record["to_updates"], record["snapshots"]) == (3, 6, [0, 2, 3])
    assert manifest(run)["update"] == 6
    later = load_config(SMOKE, [SCHEDULE, LATER])
    assert all(ckpt.read(path)[0]["fingerprint"] == later.fingerprint() for path in sealed_files(run))


def test_resuming_to_a_later_stop_without_extend_says_how(truncated, capsys):
    before = (truncated / "config.yaml").read_text()
    assert train(truncated, SCHEDULE, LATER, extra=["--resume"]) == 2
    err = capsys.readouterr().err
    assert "ppo.total_timesteps: 384 in the run, 768 now" in err and "add --extend" in err
    assert (truncated / "config.yaml").read_text() == before
    assert train(truncated, SCHEDULE, LATER, extra=["--extend"]) == 2
    assert "--extend needs --resume" in capsys.readouterr().err


@pytest.mark.parametrize(
    "overrides, message",
    [
        ((SCHEDULE, LATER, "ppo.lr=2e-3"), "only ppo.total_timesteps may change when a run is extended, but ppo.lr"),
        ((SCHEDULE, "ppo.total_timesteps=256"), "an extension cannot stop earlier"),
    ],
)
def test_what_is_no_extension_is_refused_and_the_run_left_as_it_was(truncated, tmp_path, capsys, overrides, message):
    run = tmp_path / "run"
    shutil.copytree(truncated, run)
    files = _files(run)
    assert train(run, *overrides, extra=["--resume", "--extend"]) == 2
    assert message in capsys.readouterr().err
    assert _files(run) == files


def test_a_run_that_trained_its_whole_schedule_cannot_be_extended(tmp_path):
    run = tmp_path / "whole"
    assert train(run, "ppo.total_timesteps=384", extra=["--no-eval"]) == 0
    with pytest.raises(RunDirError, match="trained its whole schedule"):
        extend_run(run, load_config(SMOKE, [LATER]))


def test_an_interrupted_extension_is_finished_by_running_it_again(truncated, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(truncated, run)
    before, later = load_config(SMOKE, [SCHEDULE, FIRST]), load_config(SMOKE, [SCHEDULE, LATER])
    half = sealed_files(run)[:3]  # as if killed after re-stamping three files
    states = {}
    for path in half:
        meta, state = ckpt.read(path, before.fingerprint())
        states[path] = state
        ckpt.save(
            path, state, later.fingerprint(), **{k: v for k, v in meta.items() if k not in ("version", "fingerprint")}
        )
    assert extend_run(run, later)["from_updates"] == 3
    for path, state in states.items():  # the states themselves are untouched
        _assert_trees_equal(ckpt.read(path, later.fingerprint())[1], state)
    assert extend_run(run, later) is None  # already extended: nothing to do


def _files(run) -> dict:
    return {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != ".lock"}


def test_a_file_of_another_run_stops_the_extension_before_anything_is_written(truncated, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(truncated, run)
    stray = ckpt.checkpoint_path(run, 1, 2)  # after seed 0's files: those must not be re-stamped first
    meta, state = ckpt.read(stray)
    ckpt.save(stray, state, "0123456789abcdef", update=meta["update"])
    before = _files(run)
    with pytest.raises(RunDirError, match=r"update_0000002.msgpack: carries fingerprint 0123456789abcdef.*nothing"):
        extend_run(run, load_config(SMOKE, [SCHEDULE, LATER]))
    assert _files(run) == before


def test_a_damaged_file_stops_the_extension_before_anything_is_written(truncated, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(truncated, run)
    damaged = ckpt.checkpoint_path(run, 1, 3)
    damaged.write_bytes(damaged.read_bytes()[:-100])
    before = _files(run)
    with pytest.raises(RunDirError, match=r"seed_1/update_0000003.msgpack: .*nothing was changed: restore the file"):
        extend_run(run, load_config(SMOKE, [SCHEDULE, LATER]))
    assert _files(run) == before


def test_mid_of_an_extended_run_is_a_snapshot_it_kept(tmp_path):
    """Snapshots of 4 updates (0, 2, 4) and of 6 (0, 3, 6) do not nest: the run extended from 4 to 6 keeps
    0, 2, 4, 6, and its "mid" is 4 (as the study runner reads it), not the never-kept 3."""
    schedule, run = "ppo.schedule_timesteps=1024", tmp_path / "run"  # an 8-update schedule
    assert train(run, schedule, "ppo.total_timesteps=512", extra=["--no-eval"]) == 0
    assert train(run, schedule, "ppo.total_timesteps=768", extra=["--resume", "--extend", "--no-eval"]) == 0
    assert ckpt.list_updates(run, 0) == ckpt.run_snapshots(run, 6, 3) == [0, 2, 4, 6]
    assert policy.load(run, checkpoint="mid").meta["update"] == 4
    assert policy.load(run, seed=1, checkpoint="final").meta["update"] == 6


@pytest.mark.parametrize("extensions", [[1], [{"snapshots": ["x"]}], [{"from_updates": 3}], {"snapshots": [0]}])
def test_a_damaged_extension_record_is_named_not_a_traceback(truncated, tmp_path, capsys, extensions):
    """manifest.json's ``extensions`` decide which snapshots an extended run kept ("mid" of the run); a record
    edited by hand or cut once ended export, xp, render and play in an AttributeError or ValueError."""
    run = tmp_path / "run"
    shutil.copytree(truncated, run)
    path = run / "manifest.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "extensions": extensions}))
    with pytest.raises(ckpt.CheckpointError, match=r"manifest.json: .*extensions"):
        ckpt.earlier_snapshots(run)
    with pytest.raises(RunDirError, match=r"manifest.json: .*extensions"):
        RunDir(run).read_manifest()
    out = tmp_path / "mid.ocv2policy"
    assert main(["export", str(run), "--checkpoint", "mid", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "manifest.json: " in err and "extensions" in err and "Traceback" not in err, err
    assert not out.exists()
