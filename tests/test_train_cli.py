"""``ocv2 train`` / ``ocv2 xp`` and the local driver: run directories, every method, resume, errors, determinism.

Every run is configs/smoke.yaml (2 seeds x 4 updates, 40-step episodes, a [8, 8] CNN). Compilation dominates
these tests; runs that build the same programs (the SP run, its resume, its rerun, the FCP partner stage)
compile once, through the session's persistent compilation cache (tests/conftest.py).
"""

from __future__ import annotations

import csv
import dataclasses
import errno
import importlib
import json
import logging
import os
import shutil
import signal
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

import ocv2.atomic
from cluster.cli import main
from cluster.runtime import coordinator, evaluate, interrupt, runstate
from cluster.runtime.rundir import METRIC_FIELDS, RunDir, RunDirError
from ocv2.atomic import is_temporary
from population import checkpoints as ckpt
from population import ppo, published
from population.config import dump_config, load_config
from population.keys import derive_key
from population.sa import collect_buffer

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")
NUM_SEEDS, NUM_UPDATES, SNAPSHOTS = 2, 4, [0, 2, 4]  # smoke.yaml: 512 steps / (4 envs x 32 steps); 3 snapshots
TIMING_COLUMNS = {"steps_per_s", "wall_s"}
cli_main = importlib.import_module("cluster.cli.main")  # the module; ``cluster.cli.main`` is also its function


def train(out, *overrides, extra=()) -> int:
    args = ["train", SMOKE, "--out", str(out), "--quiet", "--backend", "local", *extra]
    for item in overrides:
        args += ["--set", item]
    return main(args)


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def manifest(run) -> dict:
    return json.loads((Path(run) / "manifest.json").read_text())


def seed_keys(rows) -> list[tuple[int, int]]:
    return [(int(r["seed"]), int(r["update"])) for r in rows]


def _assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _raw_checkpoint(run, seed, update):
    return ckpt.read(ckpt.checkpoint_path(run, seed, update))[1]


SP_EVAL = "eval.episodes=3"  # the `ocv2 xp --episodes 3` test then reuses the compiled cross-play


@pytest.fixture(scope="module")
def sp_run(tmp_path_factory):
    """One finished SP run with evaluation (shared, never modified: tests copy it)."""
    out = tmp_path_factory.mktemp("runs") / "sp"
    assert train(out, SP_EVAL) == 0
    return out


# ---------------------------------------------------------------------------------------------------
# the run directory
# ---------------------------------------------------------------------------------------------------


def test_train_writes_the_whole_run_directory(sp_run):
    config = load_config(SMOKE, [SP_EVAL])
    assert (config.population.num_seeds, config.ppo.num_updates) == (NUM_SEEDS, NUM_UPDATES)
    assert RunDir(sp_run).load_config() == config

    info = manifest(sp_run)
    assert info["status"] == "finished" and info["method"] == "sp"
    assert info["update"] == info["num_updates"] == NUM_UPDATES
    assert info["snapshots"] == SNAPSHOTS and info["seeds"] == [0, 1] and info["pool"] == []

    rows = read_csv(sp_run / "metrics.csv")
    assert len(rows) == NUM_SEEDS * NUM_UPDATES
    assert sorted(seed_keys(rows)) == [(s, u) for s in range(NUM_SEEDS) for u in range(1, NUM_UPDATES + 1)]
    assert list(rows[0]) == list(METRIC_FIELDS) + ["return_recipe_0+0+0"]
    for r in rows:
        assert int(r["env_steps"]) == int(r["update"]) * config.ppo.steps_per_update
        assert float(r["entropy"]) > 0 and float(r["steps_per_s"]) > 0

    for seed in range(NUM_SEEDS):
        assert (sp_run / "checkpoints" / f"seed_{seed}").is_dir()
        assert ckpt.list_updates(sp_run, seed) == SNAPSHOTS  # periodic ones replaced, snapshots + final kept
        meta, _ = ckpt.read(ckpt.checkpoint_path(sp_run, seed, NUM_UPDATES), config.fingerprint())
        assert meta["seed"] == seed and meta["update"] == NUM_UPDATES and meta["method"] == "sp"

    matrix = read_csv(sp_run / "xp" / "matrix.csv")
    assert [r["seat0\\seat1"] for r in matrix] == ["seed_0", "seed_1"] and list(matrix[0])[1:] == ["seed_0", "seed_1"]
    values = np.array([[float(r[f"seed_{j}"]) for j in range(2)] for r in matrix])
    summary = json.loads((sp_run / "xp" / "summary.json").read_text())
    assert {"sp_mean", "sp_std", "xp_mean", "xp_std", "gap", "num_policies", "episodes_per_pair"} <= set(summary)
    assert summary["num_policies"] == NUM_SEEDS and summary["episodes_per_pair"] == config.eval.episodes
    assert summary["sp_mean"] == pytest.approx(np.diag(values).mean(), abs=1e-3)
    assert summary["xp_mean"] == pytest.approx((values[0, 1] + values[1, 0]) / 2, abs=1e-3)
    assert len(read_csv(sp_run / "xp" / "episodes.csv")) == NUM_SEEDS**2 * config.eval.episodes
    for image in ("xp/heatmap.png", "plots/training.png"):
        assert (sp_run / image).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    gifs = sorted((sp_run / "gifs").glob("*.gif"))
    assert len(gifs) == config.eval.gifs and gifs[0].read_bytes()[:4] == b"GIF8"
    assert not list(sp_run.rglob(".*tmp*"))  # atomic writes left no temporaries


def test_xp_command_rewrites_the_summary(sp_run, tmp_path):
    run = tmp_path / "copy"
    shutil.copytree(sp_run, run)
    original = json.loads((run / "xp" / "summary.json").read_text())
    assert original["episodes_per_pair"] == 3
    # The config now asks for 5 episodes (eval is outside the fingerprint); --episodes 3 must win.
    config = RunDir(run).load_config()
    dump_config(dataclasses.replace(config, eval=dataclasses.replace(config.eval, episodes=5)), run / "config.yaml")
    shutil.rmtree(run / "xp")
    assert main(["xp", str(run), "--episodes", "3"]) == 0
    summary = json.loads((run / "xp" / "summary.json").read_text())
    assert summary["episodes_per_pair"] == 3 and summary["num_policies"] == NUM_SEEDS
    assert len(read_csv(run / "xp" / "episodes.csv")) == NUM_SEEDS**2 * 3
    assert (run / "xp" / "matrix.csv").exists() and (run / "xp" / "heatmap.png").exists()
    # The same evaluation keys as after training: the same numbers.
    for key in ("sp_mean", "sp_std", "xp_mean", "xp_std", "gap", "per_recipe"):
        assert summary[key] == original[key]


# ---------------------------------------------------------------------------------------------------
# methods
# ---------------------------------------------------------------------------------------------------


def test_sa_saves_one_buffer_per_iteration_collected_by_the_current_policies(tmp_path, capsys, caplog):
    run = tmp_path / "sa"
    assert train(run, "population.method=sa", extra=["--no-eval"]) == 0
    assert manifest(run)["status"] == "finished" and manifest(run)["method"] == "sa"
    buffers = sorted(p.name for p in (run / "sa").iterdir())
    assert buffers == ["buffer_000.msgpack", "buffer_001.msgpack"]

    config = RunDir(run).load_config()
    trainer = ppo.make_trainer(config)
    template = runstate.state_template(trainer, 0)
    schedule = runstate.Schedule.of(config)
    assert schedule.iteration_starts == (0, 2)

    def params_at(update):
        states = [
            ckpt.load(ckpt.checkpoint_path(run, s, update), template, config.fingerprint())[1] for s in range(NUM_SEEDS)
        ]
        return jax.tree.map(lambda *xs: np.stack(xs), *(s.params for s in states))

    # The first buffer comes from the untrained networks (the update-0 checkpoint = fresh init) ...
    untrained = params_at(0)
    _assert_trees_equal(untrained, ppo.init_population(trainer, range(NUM_SEEDS)).params)
    for iteration, update in enumerate(schedule.iteration_starts):  # ... the second from the update-2 policies
        expected = collect_buffer(
            trainer.network.apply,
            runstate.hidden_size(trainer),
            ppo.eval_env(config),
            params_at(update),
            derive_key(config.population.seed, "sa", iteration),
            config.population.sa,
        )
        meta, stored = ckpt.load(run / "sa" / f"buffer_{iteration:03d}.msgpack", expected, config.fingerprint())
        assert meta["iteration"] == iteration and meta["states"] == NUM_SEEDS**2 * 2 * 4
        _assert_trees_equal(stored, expected)
    first = ckpt.read(run / "sa" / "buffer_000.msgpack")[1]
    second = ckpt.read(run / "sa" / "buffer_001.msgpack")[1]
    assert not np.array_equal(first["agents"]["x"], second["agents"]["x"])

    # Resuming at the second iteration's start (its buffer lost too) recollects the same buffer and
    # finishes bit for bit like the uninterrupted run.
    resumed = tmp_path / "sa_resumed"
    shutil.copytree(run, resumed)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(resumed, seed, NUM_UPDATES).unlink()
    (resumed / "sa" / "buffer_001.msgpack").unlink()
    assert train(resumed, "population.method=sa", extra=["--resume", "--no-eval"]) == 0
    _assert_trees_equal(ckpt.read(resumed / "sa" / "buffer_001.msgpack")[1], second)
    for seed in range(NUM_SEEDS):
        _assert_trees_equal(_raw_checkpoint(resumed, seed, NUM_UPDATES), _raw_checkpoint(run, seed, NUM_UPDATES))
    _assert_same_metrics(read_csv(resumed / "metrics.csv"), read_csv(run / "metrics.csv"))

    # With its buffer still there, a resume loads it and its progress says so: "collecting states" on every
    # resume of a 10-seed study sent a reader looking for a collection that never ran.
    kept = tmp_path / "sa_kept_buffer"
    shutil.copytree(run, kept)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(kept, seed, NUM_UPDATES).unlink()
    caplog.set_level(logging.INFO, logger="cluster")
    args = ["train", SMOKE, "--out", str(kept), "--backend", "local", "--set", "population.method=sa"]
    assert main([*args, "--resume", "--no-eval"]) == 0
    notes = [m.strip() for m in caplog.messages if "SA iteration" in m]
    assert notes == ["SA iteration 2/2: loading its states"], caplog.messages
    _assert_same_metrics(read_csv(kept / "metrics.csv"), read_csv(run / "metrics.csv"))

    # "Augment from last month's cross-play": archived states join every iteration's buffer. Every 20th
    # state instead of every 10th, so that collected + archived states are as many as the run above
    # kept: the same training programs, loaded from the compilation cache instead of compiled again.
    from cluster.archive import states_as_buffer

    archive = run / "archive" / "sa" / "iteration_001.mcap"
    augmented = tmp_path / "sa_augmented"
    sparser = ["population.sa.keep_every=20", f"population.sa.archives=[{archive}]"]
    assert train(augmented, "population.method=sa", *sparser, extra=["--no-eval"]) == 0
    collected, extended = (
        ckpt.read(run / "sa" / "buffer_000.msgpack"),
        ckpt.read(augmented / "sa" / "buffer_000.msgpack"),
    )
    archived = states_as_buffer([archive], keep_every=20)
    kept = collected[0]["states"] // 2  # t = 0, 20 of the t = 0, 10, 20, 30 above
    assert extended[0]["states"] == kept + archived.step.shape[0] == collected[0]["states"]
    head = jax.tree.map(lambda x: x[:kept], extended[1])
    tail = jax.tree.map(lambda x: x[kept:], extended[1])
    # The same episodes as the run above (same keys, untrained policies); ordered (pair, rollout, t).
    every_other = lambda x: x.reshape((-1, 4) + x.shape[1:])[:, ::2].reshape((-1,) + x.shape[1:])
    _assert_trees_equal(head, jax.tree.map(every_other, collected[1]))
    _assert_trees_equal(tail, jax.tree.map(np.asarray, serialization.to_state_dict(archived)))
    # The archive is pinned by its bytes: one that changed between sessions would feed the later iterations
    # other states than an uninterrupted run had.
    assert manifest(augmented)["sa_archives"] == {str(archive): published.sha256_of(archive)}
    shutil.copy(run / "archive" / "sa" / "iteration_000.mcap", archive)
    assert train(augmented, "population.method=sa", *sparser, extra=["--no-eval", "--resume"]) == 2
    assert f"population.sa.archives: {archive} has changed since this run started" in capsys.readouterr().err


def test_sa_archives_that_do_not_exist_fail_before_the_run_starts(tmp_path, capsys):
    run = tmp_path / "bad"
    assert train(run, "population.method=sa", "population.sa.archives=[nowhere.mcap]") == 2
    assert "nowhere.mcap" in capsys.readouterr().err
    assert not run.exists()


def test_fcp_without_partners_trains_a_partner_stage(tmp_path):
    run = tmp_path / "fcp"
    assert train(run, "population.method=fcp", extra=["--no-eval"]) == 0
    config = load_config(SMOKE, ["population.method=fcp"])
    partners = run / "partners"
    stage = RunDir(partners).load_config()
    assert stage.population.method == "sp" and stage.population.num_seeds == config.population.fcp.partner_seeds
    assert manifest(partners)["status"] == "finished"
    for seed in range(config.population.fcp.partner_seeds):
        assert ckpt.list_updates(partners, seed) == SNAPSHOTS
    info = manifest(run)
    assert info["status"] == "finished" and info["method"] == "fcp"
    fcp = config.population.fcp
    assert fcp.checkpoints == ("mid", "final")
    assert len(info["pool"]) == fcp.partner_seeds * len(fcp.checkpoints)
    assert info["pool"] == ["seed0@2", "seed0@4", "seed1@2", "seed1@4"]
    for seed in range(NUM_SEEDS):
        assert NUM_UPDATES in ckpt.list_updates(run, seed)
    assert len(read_csv(run / "metrics.csv")) == NUM_SEEDS * NUM_UPDATES


def test_fcp_reuses_a_given_partner_run(sp_run, tmp_path):
    run = tmp_path / "fcp"
    assert train(run, "population.method=fcp", f"population.fcp.partners={sp_run}", extra=["--no-eval"]) == 0
    assert not (run / "partners").exists()
    assert manifest(run)["pool"] == ["seed0@2", "seed0@4", "seed1@2", "seed1@4"]
    # The pool is exactly those checkpoints' parameters.
    config = RunDir(run).load_config()
    pool, labels = coordinator.load_pool(config, ppo.make_trainer(config), sp_run)
    assert labels == manifest(run)["pool"]
    for index, (seed, update) in enumerate([(0, 2), (0, 4), (1, 2), (1, 4)]):
        stored = _raw_checkpoint(sp_run, seed, update)["params"]
        member = jax.tree.map(lambda x: x[index], pool)
        _assert_trees_equal(member, jax.tree.map(lambda t, x: np.asarray(x), member, stored))


# The activation too: the learner's network plays the partners' parameters, so partners of another activation
# would load (the same shapes) and be played as a function they never were.
@pytest.mark.parametrize("difference", ["model.fc_dim=32", "ppo.activation=tanh"])
def test_fcp_partner_run_of_another_model_is_a_clear_error(tmp_path, capsys, difference):
    other = tmp_path / "other"
    RunDir(other).create(load_config(SMOKE, [difference]))
    assert (
        train(tmp_path / "fcp", "population.method=fcp", f"population.fcp.partners={other}", extra=["--no-eval"]) == 2
    )
    err = capsys.readouterr().err
    assert "population.fcp.partners" in err and "different env or model" in err


def test_fcp_partner_errors(tmp_path, sp_run, capsys):
    assert train(tmp_path / "a", "population.method=fcp", f"population.fcp.partners={tmp_path / 'nothing'}") == 2
    assert "population.fcp.partners" in capsys.readouterr().err
    assert (
        train(
            tmp_path / "b",
            "population.method=fcp",
            f"population.fcp.partners={sp_run}",
            "population.fcp.partner_seeds=3",
        )
        == 2
    )
    assert "population.fcp.partner_seeds" in capsys.readouterr().err


def test_op_runs_and_archives_training_episodes(tmp_path):
    run = tmp_path / "op"
    assert (
        train(run, "population.method=op", "env.layout=cramped_room_v2", "archive.train_every=2", extra=["--no-eval"])
        == 0
    )
    from cluster.archive import ArchiveReader

    assert sorted(p.name for p in (run / "archive" / "train").iterdir()) == [
        "update_0000002.mcap",
        "update_0000004.mcap",
    ]
    with ArchiveReader(run / "archive" / "train" / "update_0000004.mcap") as reader:  # one self-play episode per seed
        metas = reader.episodes()
        assert [m["seeds"] for m in metas] == [[0, 0], [1, 1]]
        assert {m["kind"] for m in metas} == {"training"} and {m["checkpoint_update"] for m in metas} == {4}
    info = manifest(run)
    assert info["status"] == "finished" and info["method"] == "op"
    config = RunDir(run).load_config()
    assert ppo.train_env(config).config.op_enabled and not ppo.eval_env(config).config.op_enabled
    assert len(read_csv(run / "metrics.csv")) == NUM_SEEDS * NUM_UPDATES
    for seed in range(NUM_SEEDS):
        assert ckpt.list_updates(run, seed) == SNAPSHOTS


def test_a_training_archive_a_kill_prevented_is_written_on_resume(tmp_path, monkeypatch):
    """Killed after update 2's checkpoints, before its training archive: the resume started after update 2 and
    archive/train/update_0000002.mcap was never written."""
    from cluster.archive import ArchiveReader
    from cluster.runtime.local import LocalWorkers

    config = load_config(SMOKE, ["archive.train_every=2", "run.checkpoint_every=2"])
    coordinator.train(config, tmp_path / "whole", LocalWorkers, show_progress=False, evaluate=False)
    real = coordinator._archive_training

    def killed(config, run, workers, before, stop):
        if stop == 2:
            raise SystemExit("killed")
        real(config, run, workers, before, stop)

    monkeypatch.setattr(coordinator, "_archive_training", killed)
    with pytest.raises(SystemExit):
        coordinator.train(config, tmp_path / "killed", LocalWorkers, show_progress=False, evaluate=False)
    monkeypatch.setattr(coordinator, "_archive_training", real)
    assert not (tmp_path / "killed" / "archive" / "train" / "update_0000002.mcap").exists()
    coordinator.train(config, tmp_path / "killed", LocalWorkers, resume=True, show_progress=False, evaluate=False)
    for update in (2, 4):
        name = f"update_{update:07d}.mcap"
        with ArchiveReader(tmp_path / "whole" / "archive" / "train" / name) as whole:
            with ArchiveReader(tmp_path / "killed" / "archive" / "train" / name) as resumed:
                assert len(resumed) == len(whole) == NUM_SEEDS
                for index in range(NUM_SEEDS):
                    np.testing.assert_array_equal(resumed.episode(index).actions, whole.episode(index).actions)
    # Killed after the archive's first seed: the user follows the advice and recovers the .partial, which takes the
    # archive's own name with one episode of two; the resume writes it again whole rather than take it as done.
    real_record, calls = coordinator.record_episodes, []

    def killed_after_one(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise SystemExit("killed")
        return real_record(*args, **kwargs)

    monkeypatch.setattr(coordinator, "record_episodes", killed_after_one)
    with pytest.raises(SystemExit):
        coordinator.train(config, tmp_path / "cut", LocalWorkers, show_progress=False, evaluate=False)
    monkeypatch.setattr(coordinator, "record_episodes", real_record)
    cut = tmp_path / "cut" / "archive" / "train" / "update_0000002.mcap"
    assert main(["archive", "recover", f"{cut}.partial"]) == 0 and len(ArchiveReader(cut)) == 1
    coordinator.train(config, tmp_path / "cut", LocalWorkers, resume=True, show_progress=False, evaluate=False)
    with ArchiveReader(cut) as resumed, ArchiveReader(tmp_path / "whole" / "archive" / "train" / cut.name) as whole:
        assert len(resumed) == NUM_SEEDS
        for index in range(NUM_SEEDS):
            np.testing.assert_array_equal(resumed.episode(index).actions, whole.episode(index).actions)


# ---------------------------------------------------------------------------------------------------
# resume and determinism
# ---------------------------------------------------------------------------------------------------


def test_resume_after_an_interruption_matches_the_uninterrupted_run(sp_run, tmp_path):
    run = tmp_path / "interrupted"
    # As if killed after update 4's metrics were written but before its checkpoints were.
    _without_final_checkpoints(sp_run, run)
    assert len(read_csv(run / "metrics.csv")) == NUM_SEEDS * NUM_UPDATES  # rows 3..4 already there

    assert train(run, extra=["--resume", "--no-eval"]) == 0
    assert manifest(run)["status"] == "finished" and manifest(run)["update"] == NUM_UPDATES
    for seed in range(NUM_SEEDS):  # whole TrainStates, bit for bit
        _assert_trees_equal(_raw_checkpoint(run, seed, NUM_UPDATES), _raw_checkpoint(sp_run, seed, NUM_UPDATES))
    _, _, resumed = evaluate.final_params(run)
    _, _, original = evaluate.final_params(sp_run)
    _assert_trees_equal(resumed, original)

    rows = read_csv(run / "metrics.csv")
    keys = seed_keys(rows)
    assert len(keys) == len(set(keys)) == NUM_SEEDS * NUM_UPDATES
    _assert_same_metrics(rows, read_csv(sp_run / "metrics.csv"))


def _without_final_checkpoints(sp_run, run):
    """A copy of the SP run with the last update's checkpoints and the evaluation gone, manifest at update 2."""
    shutil.copytree(sp_run, run)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(run, seed, NUM_UPDATES).unlink()
    for sub in ("xp", "plots", "gifs"):
        shutil.rmtree(run / sub)
    RunDir(run).update_manifest(status="training", update=2)


def _interrupted_at_update_2(sp_run, run):
    """A copy of the SP run as if its driver was killed after update 2's chunk was complete."""
    _without_final_checkpoints(sp_run, run)
    _keep_metrics_through(run, 2)


def _keep_metrics_through(run, update: int) -> None:
    """metrics.csv as the driver had written it after ``update``: the rows of later updates gone."""
    with open(run / "metrics.csv", newline="") as handle:
        header, *rows = handle.read().splitlines(keepends=True)
    kept = [row for row in rows if int(row.split(",")[1]) <= update]
    (run / "metrics.csv").write_bytes((header + "".join(kept)).encode())


def _assert_same_run(run, reference):
    for seed in range(NUM_SEEDS):
        _assert_trees_equal(_raw_checkpoint(run, seed, NUM_UPDATES), _raw_checkpoint(reference, seed, NUM_UPDATES))
    _assert_same_metrics(read_csv(run / "metrics.csv"), read_csv(reference / "metrics.csv"))


@pytest.fixture
def terminal_sigint():
    """SIGINT as in a terminal. Tests run by a background job (nohup, `&` in a script, some CI runners)
    inherit SIGINT ignored, and then ChunkWait rightly leaves Ctrl-C alone."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _ctrl_c_while_polling(monkeypatch, presses: int, signum: int = signal.SIGINT) -> None:
    """A real ``signum`` (SIGINT by default) at each of the first ``presses`` polls of the first training chunk."""
    if signum == signal.SIGINT:
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the terminal_sigint fixture
    ready = interrupt._ready
    left = [presses]

    def pressed(tree):
        if left[0]:
            left[0] -= 1
            signal.raise_signal(signum)
        return ready(tree)

    monkeypatch.setattr(interrupt, "_ready", pressed)


def test_ctrl_c_lets_the_running_chunk_finish_and_save_then_stops(
    sp_run, tmp_path, capsys, monkeypatch, terminal_sigint
):
    run = tmp_path / "ctrl_c"
    _ctrl_c_while_polling(monkeypatch, presses=1)
    assert train(run, SP_EVAL) == 130
    err = capsys.readouterr().err
    assert "Ctrl-C: letting updates 1-2 finish" in err and "press Ctrl-C again to stop now" in err
    assert "resuming continues from update 0" in err and "ocv2 train: interrupted" in err
    assert all(ckpt.list_updates(run, seed) == [0, 2] for seed in range(NUM_SEEDS))  # the chunk was saved
    assert manifest(run)["update"] == 2 and len(read_csv(run / "metrics.csv")) == NUM_SEEDS * 2
    assert train(run, SP_EVAL, extra=["--resume", "--no-eval"]) == 0
    _assert_same_run(run, sp_run)


def test_sigterm_stops_like_ctrl_c_even_where_sigint_is_ignored(sp_run, tmp_path, capsys, monkeypatch):
    """A run started in the background ignores SIGINT; SIGTERM (what study_state/stop_and_pack.py and service
    managers send) lets the chunk in flight finish and be saved, then stops. Outside the command, SIGTERM keeps
    its own meaning."""
    exits = []
    monkeypatch.setattr(cli_main, "exit_now", exits.append)  # a regression must fail here, not end the worker
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    # As in a fresh process: an earlier Ray test in this worker leaves ray.init's own SIGTERM handler behind.
    previous_term = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        run = tmp_path / "sigterm"
        _ctrl_c_while_polling(monkeypatch, presses=1, signum=signal.SIGTERM)
        assert train(run, SP_EVAL) == 130
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL and exits == []  # stopped after the chunk
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
    err = capsys.readouterr().err
    assert "SIGTERM: letting updates 1-2 finish" in err and "send SIGTERM or press Ctrl-C again" in err
    assert all(ckpt.list_updates(run, seed) == [0, 2] for seed in range(NUM_SEEDS))  # the chunk was saved
    assert train(run, SP_EVAL, extra=["--resume", "--no-eval"]) == 0
    _assert_same_run(run, sp_run)


def test_an_interrupt_outside_a_chunk_wait_ends_the_process_without_waiting_for_xla(monkeypatch, capsys):
    """Ctrl-C while a program compiles or cross-play runs: returning normally let the interpreter shut down under
    XLA's running threads, which sometimes aborted ("pure virtual method called", exit 134). A stop after a
    saved chunk has nothing running and returns as usual."""
    exits = []
    monkeypatch.setattr(cli_main, "exit_now", exits.append)
    monkeypatch.setattr(cli_main, "jax_started", lambda: True)
    original = cli_main.resolve
    for raised, expected in [(KeyboardInterrupt, [130]), (interrupt.StoppedAfterChunk, [])]:
        exits.clear()

        def command(_args, raised=raised):
            raise raised

        def resolve(target, command=command):  # `ocv2 layouts` runs `command`; the parser is built as usual
            return command if target is cli_main._cmd_layouts else original(target)

        monkeypatch.setattr(cli_main, "resolve", resolve)
        assert main(["layouts"]) == 130
        assert exits == expected and "ocv2 layouts: interrupted" in capsys.readouterr().err


def test_a_second_ctrl_c_stops_at_once_and_the_run_resumes_from_its_last_checkpoint(
    sp_run, tmp_path, capsys, monkeypatch, terminal_sigint
):
    run = tmp_path / "ctrl_c_twice"
    exits = []
    monkeypatch.setattr(cli_main, "exit_now", exits.append)  # os._exit would end pytest too
    _ctrl_c_while_polling(monkeypatch, presses=2)
    assert train(run, SP_EVAL) == 130
    assert exits == [130]  # the chunk still runs on XLA's threads: the process ends without waiting for it
    err = capsys.readouterr().err
    assert "second Ctrl-C: stopping now without updates 1-2; resuming continues from update 0" in err
    assert all(ckpt.list_updates(run, seed) == [0] for seed in range(NUM_SEEDS))
    assert manifest(run)["update"] == 0
    assert train(run, SP_EVAL, extra=["--resume", "--no-eval"]) == 0
    _assert_same_run(run, sp_run)


def test_a_full_disk_is_a_one_line_error_and_the_run_resumes(sp_run, tmp_path, capsys, monkeypatch):
    run = tmp_path / "full"
    _interrupted_at_update_2(sp_run, run)
    metrics_before = (run / "metrics.csv").read_bytes()
    writes = []
    fsync = ocv2.atomic._fsync_path

    def disk_fills_at_the_metrics_write(path):
        # The update-4 checkpoints fit; the metrics.csv write after them (and all after it) does not.
        if Path(path).name.startswith(".") and (writes or Path(path).name.startswith(".metrics")):
            writes.append(path)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        fsync(path)

    monkeypatch.setattr(ocv2.atomic, "_fsync_path", disk_fills_at_the_metrics_write)
    assert train(run, extra=["--resume", "--no-eval"]) == 1  # a failure, not a usage error
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "No space left on device" in err
    assert f"continue with `ocv2 train {SMOKE} --out {run} --backend local --resume`" in err  # as it was started
    assert (run / "metrics.csv").read_bytes() == metrics_before  # untouched, not half-written
    assert all(ckpt.list_updates(run, seed) == SNAPSHOTS for seed in range(NUM_SEEDS))
    assert not [p for p in run.rglob("*") if is_temporary(p)]
    monkeypatch.setattr(ocv2.atomic, "_fsync_path", fsync)  # space freed
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    assert manifest(run)["status"] == "finished"
    _assert_same_run(run, sp_run)  # update 3-4 rows come back from the update-4 checkpoints' meta


def test_a_run_that_could_not_start_is_not_told_to_resume(tmp_path, capsys, monkeypatch):
    """A read-only --out once got "keeps its last complete checkpoint ... continue with --resume", with nothing
    to resume and without the run's --set overrides."""

    def read_only(path):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))

    monkeypatch.setattr(ocv2.atomic, "_fsync_path", read_only)
    assert train(tmp_path / "ro", "ppo.lr=1e-3", extra=["--no-eval"]) == 1
    err = capsys.readouterr().err.strip()
    assert "nothing was trained" in err and "--resume" not in err
    assert f"`ocv2 train {SMOKE} --out {tmp_path / 'ro'} --set ppo.lr=1e-3 --backend local` again" in err


def test_resume_refills_a_dropped_last_metrics_row_from_the_checkpoint(sp_run, tmp_path, capsys):
    run = tmp_path / "torn"
    shutil.copytree(sp_run, run)
    text = (run / "metrics.csv").read_text()
    (run / "metrics.csv").write_text(text[:-12])  # the last row (seed 1, update 4) cut short
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    assert "incomplete (an interrupted write)" in capsys.readouterr().err
    assert (run / "metrics.csv").read_text() == text  # the row came back from the update-4 checkpoint's meta


def test_resume_refuses_a_metrics_file_cut_before_the_last_chunk(sp_run, tmp_path, capsys):
    """Only the last chunk's rows (updates 3-4) come back from the checkpoints: a file cut further back, or
    emptied, once trained on and lost updates 1-2 for good without a word."""
    run = tmp_path / "cut"
    shutil.copytree(sp_run, run)
    text = (run / "metrics.csv").read_text()
    for damaged in (text[: len(text) // 3], ""):
        (run / "metrics.csv").write_text(damaged)
        before = {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()}
        assert train(run, extra=["--resume", "--no-eval"]) == 2
        err = capsys.readouterr().err
        assert f"{run / 'metrics.csv'}: lacks the rows of" in err and "between updates 1 and 2" in err, err
        assert "Restore it from a copy" in err
        assert {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()} == before
    (run / "metrics.csv").write_text(text)  # restored: it resumes
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    assert (run / "metrics.csv").read_text() == text


def test_resume_refuses_a_damaged_metrics_row_naming_it_and_leaves_the_file_as_it_was(sp_run, tmp_path, capsys):
    """A damaged row before the last (line 3: seed 0, update 2) was deleted from disk before the resume refused,
    and the refusal blamed a cut file."""
    run = tmp_path / "damaged"
    shutil.copytree(sp_run, run)
    text = (run / "metrics.csv").read_bytes()
    lines = text.decode().splitlines(keepends=True)
    lines[2] = lines[2].replace(",", ";", 3)
    damaged = "".join(lines).encode()
    (run / "metrics.csv").write_bytes(damaged)
    assert train(run, extra=["--resume", "--no-eval"]) == 2
    err = capsys.readouterr().err
    assert "the file is damaged: line 3 (row 2) is not a complete metrics row (0;2;" in err, err
    assert "cut or emptied" not in err and "nothing was trained and the file was not changed" in err
    assert (run / "metrics.csv").read_bytes() == damaged
    (run / "metrics.csv").write_bytes(text)  # repaired: it resumes, the file as it was
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    assert (run / "metrics.csv").read_bytes() == text


def test_metrics_rebuilt_from_checkpoints_keep_the_column_order_of_a_straight_run(sp_run, tmp_path):
    """Killed after the first chunk's checkpoints but before its rows reached metrics.csv: the rows come back from
    the checkpoints' meta, whose keys are sorted, and once made the header (actor_loss,approx_kl,...)."""
    run = tmp_path / "no_metrics"
    _without_final_checkpoints(sp_run, run)
    (run / "metrics.csv").unlink()
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    with open(run / "metrics.csv", newline="") as mine, open(sp_run / "metrics.csv", newline="") as straight:
        assert mine.readline() == straight.readline() == ",".join([*METRIC_FIELDS, "return_recipe_0+0+0"]) + "\r\n"
    _assert_same_metrics(read_csv(run / "metrics.csv"), read_csv(sp_run / "metrics.csv"))
    assert seed_keys(read_csv(run / "metrics.csv")) == seed_keys(read_csv(sp_run / "metrics.csv"))


def test_a_corrupt_latest_checkpoint_falls_back_to_the_previous_one(sp_run, tmp_path, capsys):
    run = tmp_path / "corrupt"
    shutil.copytree(sp_run, run)
    path = ckpt.checkpoint_path(run, 1, NUM_UPDATES)
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # inside the state bytes: the file still parses, only the checksum tells
    path.write_bytes(bytes(data))
    assert train(run, extra=["--resume", "--no-eval"]) == 0
    err = capsys.readouterr().err
    assert f"{path}: checksum mismatch" in err and "falling back to update 2" in err
    _assert_same_run(run, sp_run)  # updates 3-4 trained again, to the same numbers


def test_resuming_with_fewer_snapshots_keeps_those_the_run_was_created_with(sp_run, tmp_path):
    run = tmp_path / "fewer"
    _interrupted_at_update_2(sp_run, run)
    assert train(run, "run.num_checkpoints=2", extra=["--resume", "--no-eval"]) == 0
    assert manifest(run)["snapshots"] == [0, 4]
    assert all(ckpt.list_updates(run, seed) == SNAPSHOTS for seed in range(NUM_SEEDS))
    # An FCP run reads the snapshots this run's config.yaml names ("mid" = update 2): still there.
    config = load_config(SMOKE, ["population.method=fcp", f"population.fcp.partners={run}"])
    _, labels = coordinator.load_pool(config, ppo.make_trainer(config), run)
    assert labels == ["seed0@2", "seed0@4", "seed1@2", "seed1@4"]


def _assert_same_metrics(rows, reference):
    index = {(int(r["seed"]), int(r["update"])): r for r in reference}
    assert len(rows) == len(index)
    for row in rows:
        other = index[(int(row["seed"]), int(row["update"]))]
        assert set(row) == set(other)
        for column in row:
            if column not in TIMING_COLUMNS:
                assert row[column] == other[column], (column, row, other)


def test_two_fresh_runs_are_identical(sp_run, tmp_path):
    run = tmp_path / "again"
    assert train(run, extra=["--no-eval"]) == 0
    _assert_same_metrics(read_csv(run / "metrics.csv"), read_csv(sp_run / "metrics.csv"))
    for seed in range(NUM_SEEDS):
        for update in SNAPSHOTS:
            _assert_trees_equal(_raw_checkpoint(run, seed, update), _raw_checkpoint(sp_run, seed, update))


# ---------------------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------------------


def test_existing_run_without_resume_is_refused(sp_run, capsys):
    before = (sp_run / "manifest.json").read_text()
    assert train(sp_run) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert (sp_run / "manifest.json").read_text() == before


def test_non_run_directory_is_refused(tmp_path, capsys):
    (tmp_path / "stuff.txt").write_text("x")
    assert train(tmp_path) == 2
    assert "not an ocv2 run directory" in capsys.readouterr().err


@pytest.mark.parametrize(
    "override, key",
    [
        ("ppo.num_minibatches=3", "ppo.num_minibatches"),
        ("ppo.bogus=1", "ppo.bogus"),
        ("population.method=xx", "population.method"),
        ("ppo.total_timesteps=1e30", "ppo.total_timesteps"),  # int32
        ("ppo.lr=1e308", "ppo.lr"),  # inf in float32
        ("run.num_checkpoints=1000000000", "run.num_checkpoints"),  # hung computing 1e9 snapshot updates
    ],
)
def test_config_errors_exit_2_naming_the_key(tmp_path, capsys, override, key):
    assert train(tmp_path / "run", override) == 2
    assert f"--set {override}: {key}" in capsys.readouterr().err  # the override, not the file, is named
    assert not (tmp_path / "run").exists()


def test_resume_with_a_different_config_is_refused(sp_run, capsys):
    assert train(sp_run, "ppo.lr=2e-3", "eval.episodes=5", extra=["--resume"]) == 2
    err = capsys.readouterr().err
    assert "different config" in err and "ppo.lr: " in err and "0.002 now" in err  # the key, not only a hash
    assert "eval.episodes" not in err  # not fingerprinted: it may change on resume


def test_resume_needs_a_run(tmp_path, capsys):
    assert train(tmp_path / "none", extra=["--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert main(["train", SMOKE, "--resume", "--quiet", "--backend", "local"]) == 2
    assert "--resume needs --out" in capsys.readouterr().err


def test_xp_on_a_non_run_directory_exits_2(tmp_path, capsys):
    assert main(["xp", str(tmp_path)]) == 2
    assert "not an ocv2 run directory" in capsys.readouterr().err
    assert main(["xp", str(tmp_path / "missing")]) == 2
    assert main(["xp", str(tmp_path), "--episodes", "0"]) == 2


@pytest.mark.parametrize(
    "argv, said",
    [
        (["xp", "RUN", "--seed", "4294967296"], "--seed: expected a seed in [0, 4294967295]"),  # would wrap onto 0
        (["xp", "RUN", "--seed", "-1"], "--seed: expected a non-negative integer"),
        (["export", "RUN", "--out", "p.ocv2policy", "--seed", "-1"], "--seed: expected a non-negative integer"),
    ],
)
def test_seeds_that_a_prng_key_cannot_hold_are_refused_by_name(tmp_path, capsys, argv, said):
    assert main([str(tmp_path) if a == "RUN" else a for a in argv]) == 2
    assert said in capsys.readouterr().err


def test_xp_refuses_a_source_given_twice_in_one_list(tmp_path, capsys):
    """Given twice, a source was its own partner under two labels: its self-play counted as cross-play."""
    policy = tmp_path / "a.ocv2policy"
    policy.write_bytes(b"")  # refused before anything is read
    same = [str(policy), str(tmp_path / "." / "a.ocv2policy")]
    assert main(["xp", "--rows", *same, "--backend", "local"]) == 2
    assert f"--rows: {same[1]} is given twice (also as {same[0]})" in capsys.readouterr().err
    assert main(["xp", "--rows", str(policy), "--cols", "human-proxy:coord_ring", "human-proxy:coord_ring"]) == 2
    assert "--cols: human-proxy:coord_ring is given twice" in capsys.readouterr().err


def test_checkpoint_of_another_config_is_refused(sp_run, tmp_path, capsys):
    # A second run directory whose config differs only in ppo.lr, holding the first run's checkpoints.
    other = tmp_path / "other"
    config = load_config(SMOKE, ["ppo.lr=2e-3"])
    RunDir(other).create(config)
    shutil.copytree(sp_run / "checkpoints", other / "checkpoints")
    with pytest.raises(ckpt.CheckpointError, match="different config"):
        evaluate.final_params(other)
    with pytest.raises(ckpt.CheckpointError, match="different config"):
        evaluate.evaluate_run(other, episodes=1, show_progress=False)
    assert main(["xp", str(other), "--episodes", "1"]) == 2
    assert "different config" in capsys.readouterr().err
    # Resuming it is refused the same way (the checkpoints, not the directory, are foreign).
    assert train(other, "ppo.lr=2e-3", extra=["--resume", "--no-eval"]) == 2
    assert "different config" in capsys.readouterr().err


def test_unfinished_run_cannot_be_evaluated(sp_run, tmp_path, capsys):
    run = tmp_path / "unfinished"
    shutil.copytree(sp_run, run)
    for seed in range(NUM_SEEDS):
        ckpt.checkpoint_path(run, seed, NUM_UPDATES).unlink()
    with pytest.raises(RunDirError, match="has not finished training"):
        evaluate.final_params(run)
    assert main(["xp", str(run)]) == 2
    assert "resume the run first" in capsys.readouterr().err


def test_schedule_stops_at_snapshots_checkpoints_and_sa_iterations():
    schedule = runstate.Schedule.of(load_config(SMOKE, ["population.method=sa", "run.checkpoint_every=3"]))
    assert schedule.snapshots == (0, 2, 4) and schedule.iteration_starts == (0, 2)
    stops, update = [], 0
    while update < schedule.num_updates:
        update = schedule.next_stop(update)
        stops.append(update)
    assert stops == [2, 3, 4]
    assert [schedule.iteration_at(u) for u in range(4)] == [0, 0, 1, 1]
    assert dataclasses.replace(schedule, iteration_starts=()).next_stop(0) == 2


def test_one_training_program_per_run(tmp_path, monkeypatch, fresh_programs):
    """Chunks of 3, 1 and 2 updates (an SA run of 6 updates: iteration start 3, snapshot 3, checkpoint 4)
    all run one compiled program: the chunk length is an argument of it (``ppo.make_advance_chunks``).

    Traces are counted with a Python side effect in the traced function, which runs once per program
    JAX builds (a compile-cache hit still traces, so this counts programs, not cache misses). A second
    run of the same config in the process traces nothing (``ppo.make_trainer`` and the programs built
    from it are cached per config) and gives the same numbers.
    """
    overrides = ["population.method=sa", "ppo.total_timesteps=768", "run.checkpoint_every=4"]
    schedule = runstate.Schedule.of(load_config(SMOKE, overrides))
    stops, update = [], 0
    while update < schedule.num_updates:
        stops.append(schedule.next_stop(update) - update)
        update += stops[-1]
    assert stops == [3, 1, 2] and schedule.longest_chunk == 4
    traces = []
    advance_upto = ppo.advance_upto

    def counted(trainer, state, count, max_updates, *args):
        traces.append(max_updates)
        return advance_upto(trainer, state, count, max_updates, *args)

    monkeypatch.setattr(ppo, "advance_upto", counted)
    run = tmp_path / "sa"
    assert train(run, *overrides, extra=["--no-eval"]) == 0
    assert traces == [4]
    again = tmp_path / "again"
    assert train(again, *overrides, extra=["--no-eval"]) == 0
    assert traces == [4]
    rows, rows_again = read_csv(run / "metrics.csv"), read_csv(again / "metrics.csv")
    _assert_same_metrics(rows_again, rows)
    assert seed_keys(rows_again) == seed_keys(rows)  # in the same order too
    assert sorted(seed_keys(rows)) == [(s, u) for s in range(NUM_SEEDS) for u in range(1, 7)]
    assert all(float(r["entropy"]) > 0 for r in rows)  # no padding row (all zeros) slipped into the metrics
