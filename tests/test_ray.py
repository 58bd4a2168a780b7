"""The Ray backend on a real local Ray: SA, FCP, cross-play equal to the local backend, a worker
killed with SIGKILL mid-training, a killed driver resumed, bad input, and the quickstart.

Every run is configs/smoke.yaml (2 seeds, one actor each). One Ray instance serves the whole session
(``tests/conftest.py``). Actors are fresh processes: they compile their programs or, when this process
or an earlier actor compiled the same ones, load them from the session's persistent compilation cache.
So the reference run trains here, on in-process shards shaped like the actors' (one seed each): the
same programs, compiled once instead of by two actors at once, and the actors of the later runs of
that config load them (the FCP and quickstart runs compile their own).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from cluster.archive import ArchiveReader
from cluster.cli import main
from cluster.runtime import coordinator, evaluate, ray_backend, runstate
from cluster.runtime.interrupt import ChunkAbandoned
from cluster.runtime.local import LocalWorkers
from cluster.runtime.rundir import RunDir, RunDirError
from cluster.runtime.shard import AdvanceResult, SeedShard
from population import checkpoints as ckpt
from population import ppo
from population.config import dump_config, load_config
from population.config import shards as seed_shards
from population.keys import derive_key
from population.sa import collect_buffer

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")
LONGER = ["ppo.total_timesteps=1024", "run.checkpoint_every=2"]  # 8 updates, a checkpoint every 2
SA = [*LONGER, "population.method=sa"]  # two SA iterations: state buffers gathered at updates 0 and 4
TIMING = {"steps_per_s", "wall_s"}


def train(out, *overrides, extra=()) -> int:
    args = ["train", SMOKE, "--out", str(out), "--quiet", "--backend", "ray", *extra]
    for item in overrides:
        args += ["--set", item]
    return main(args)


def final_params(run):
    return evaluate.final_params(run)[2]


def metrics_without_timing(run):
    return [{k: v for k, v in row.items() if k not in TIMING} for row in RunDir(run).read_metrics()]


def assert_same_tree(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


class ShardsHere:
    """The Ray backend's shards (``seed_shards``: one seed each), as in-process ``SeedShard``s."""

    def __init__(self, config, run_dir, pool=None):
        self.shards, self.events = seed_shards(config), []
        self.targets = [SeedShard(config, run_dir, seeds, pool) for seeds in self.shards]

    def call(self, method, jobs):
        return [getattr(self.targets[shard], method)(*args) for shard, args in jobs]

    def share(self, value):
        return value

    def restarts(self) -> int:
        return 0

    def close(self) -> None:
        self.targets = []


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted 8-update SP run, the actors' programs trained here: what the Ray runs of the
    fault-tolerance tests must reproduce (so they also show that an actor computes what this process does)."""
    run = tmp_path_factory.mktemp("ray") / "reference"
    config = load_config(SMOKE, LONGER)
    assert [len(shard) for shard in seed_shards(config)] == [1, 1]  # as on Ray: one actor per seed
    coordinator.train(config, run, ShardsHere, show_progress=False, evaluate=False)
    assert RunDir(run).read_manifest()["status"] == "finished"
    return run


def xp_archive(run):
    """{(seat-0 seed, seat-1 seed, pair episode): (return, actions)} of every file in archive/xp/."""
    episodes = {}
    for path in sorted((run / "archive" / "xp").iterdir()):
        with ArchiveReader(path) as reader:
            for index in range(len(reader)):
                episode = reader.episode(index)
                key = (*episode.meta["seeds"], episode.meta["pair_episode"])
                assert key not in episodes  # no episode stored twice
                episodes[key] = (float(episode.rewards.sum()), episode.actions)
    return episodes


def test_cross_play_spread_over_ray_workers_equals_the_local_backend(reference, ray_session):
    """Pairs spread over two actors give the matrix and archived episodes computed in one process,
    and every scored episode is in the archive (once). In-process first: the actors play the same
    row programs, and load them from the compilation cache."""
    here = evaluate.evaluate_run(reference, episodes=3, show_progress=False)
    here_csv = (reference / "xp" / "episodes.csv").read_text()
    here_archive = xp_archive(reference)
    config = RunDir(reference).load_config()
    workers = ray_backend.RayWorkers(config, reference)
    try:
        spread = evaluate.evaluate_run(reference, episodes=3, show_progress=False, workers=workers)
    finally:
        workers.close()
    spread_csv = (reference / "xp" / "episodes.csv").read_text()
    assert spread_csv == here_csv
    assert {k: v for k, v in here.items() if k != "wall_s"} == {k: v for k, v in spread.items() if k != "wall_s"}
    archive = xp_archive(reference)
    assert sorted(archive) == [(i, j, e) for i in (0, 1) for j in (0, 1) for e in range(3)]
    scored = {
        (int(r["seat0"]), int(r["seat1"]), int(r["episode"])): float(r["return"])
        for r in csv.DictReader(io.StringIO(spread_csv))
    }
    for key, (ret, actions) in archive.items():
        assert ret == scored[key]  # the archived episodes are the scored ones
        np.testing.assert_array_equal(actions, here_archive[key][1])


class Died(Exception):
    pass


def killed_between_shards(run) -> None:
    """The reference run's shards ([0], [1]) killed as the chunk to update 4 ends: seed 0 has saved it, seed 1
    has not, and the coordinator has merged update 2."""

    class SecondShardDies(ShardsHere):
        def call(self, method, jobs):
            if method == "advance" and any(args[0] == 4 for _, args in jobs):
                self.targets[0].advance(*jobs[0][1])
                raise Died
            return super().call(method, jobs)

    with pytest.raises(Died):
        coordinator.train(load_config(SMOKE, LONGER), run, SecondShardDies, show_progress=False, evaluate=False)
    assert ckpt.list_updates(run, 0)[-1] == 4 and ckpt.list_updates(run, 1)[-1] == 2


def test_a_resume_that_groups_the_seeds_otherwise_starts_where_the_coordinator_stood(tmp_path, reference):
    """Seed 0 pruned update 2 once it saved 4, so one local shard holding seeds 0 and 1 shared only the
    snapshot at update 0 and trained everything again without a word."""
    run = tmp_path / "regrouped"
    killed_between_shards(run)
    coordinator.train(load_config(SMOKE, LONGER), run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    manifest = RunDir(run).read_manifest()
    assert manifest["resumed_from"] == 2 and manifest["status"] == "finished"
    rows = metrics_without_timing(run)  # one vmapped shard sums in other orders than two: compare keys after 2
    assert sorted((r["seed"], r["update"]) for r in rows) == sorted(
        (r["seed"], r["update"]) for r in metrics_without_timing(reference)
    )
    assert [r for r in rows if int(r["update"]) <= 2] == [
        r for r in metrics_without_timing(reference) if int(r["update"]) <= 2
    ]


def test_a_shard_ahead_of_the_others_gives_each_metrics_row_once(tmp_path, reference):
    """Resumed with checkpoints every update, seed 0's shard (at update 4, the others at 2) returned its rows
    of updates 3-4 at the stop at 3 and update 4's again at the stop at 4: metrics.csv held it twice."""
    run = tmp_path / "ahead"
    killed_between_shards(run)
    finer = load_config(SMOKE, [*LONGER, "run.checkpoint_every=1"])
    coordinator.train(finer, run, ShardsHere, resume=True, show_progress=False, evaluate=False)
    assert_same_tree(final_params(run), final_params(reference))
    by_row = lambda rows: sorted(rows, key=lambda r: (int(r["seed"]), int(r["update"])))  # noqa: E731
    assert by_row(metrics_without_timing(run)) == by_row(metrics_without_timing(reference))  # chunked otherwise


def kill_later(pid: int, delay_s: float = 0.05) -> threading.Timer:
    """SIGKILL ``pid`` in ``delay_s`` (while the call just submitted to it runs); join the timer to know it fired.
    A process already gone is no error."""

    def kill():
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)

    timer = threading.Timer(delay_s, kill)
    timer.start()
    return timer


def kill_actor_in_chunk(after_update: int, shard: int = 0):
    """An ``on_chunk`` hook that SIGKILLs shard ``shard``'s actor while it trains the chunk after ``after_update``;
    the list it returns gets the kill's timer."""
    killed = []

    def hook(update, workers, _rows):
        if update == after_update and not killed:
            killed.append(kill_later(workers.pids()[shard]))

    return hook, killed


def test_a_worker_killed_mid_training_restarts_and_finishes_with_the_same_numbers(tmp_path, reference, ray_session):
    config = load_config(SMOKE, LONGER)
    run = tmp_path / "killed"
    hook, killed = kill_actor_in_chunk(2)
    summary = ray_backend.train_population(config, run, show_progress=False, evaluate=False, on_chunk=hook)
    killed.pop().join()
    assert summary["restarts"] >= 1
    assert RunDir(run).read_manifest()["restarts"] >= 1
    # At most one checkpoint interval was lost: the restarted actor came back at update >= 2.
    events = RunDir(run).read_manifest()["restart_events"]
    assert events and all(event["restored_update"] >= 2 for event in events)
    assert_same_tree(final_params(run), final_params(reference))
    assert metrics_without_timing(run) == metrics_without_timing(reference)


@pytest.fixture(scope="module")
def sa_reference(tmp_path_factory):
    """``reference`` with state augmentation: the coordinator gathers a state buffer at updates 0 and 4 and every
    actor trains against the newest; what an SA run whose actor was killed must reproduce."""
    run = tmp_path_factory.mktemp("ray") / "sa_reference"
    coordinator.train(load_config(SMOKE, SA), run, ShardsHere, show_progress=False, evaluate=False)
    return run


def test_an_sa_actor_killed_after_the_buffer_restarts_and_finishes_with_the_same_numbers(
    tmp_path, sa_reference, ray_session
):
    """Killed while it trains the chunk from update 4 with the state buffer of SA's second iteration (gathered at
    update 4), the restarted actor comes back from its checkpoint there and is sent that chunk again with that buffer:
    the run ends as the uninterrupted one, bit for bit."""
    run = tmp_path / "sa_killed"
    killed = []

    class KilledWithTheSecondBuffer(ray_backend.RayWorkers):
        def call(self, method, jobs):
            jobs = list(jobs)
            if method == "advance" and jobs[0][1][2] == 4 and not killed:  # (stop, buffer, update): from update 4
                killed.append(kill_later(self.pids()[0]))
            return super().call(method, jobs)

    summary = coordinator.train(
        load_config(SMOKE, SA), run, KilledWithTheSecondBuffer, show_progress=False, evaluate=False
    )
    killed.pop().join()
    assert summary["restarts"] >= 1
    events = RunDir(run).read_manifest()["restart_events"]
    assert events and all(e["method"] == "advance" and e["restored_update"] == 4 for e in events)
    assert_same_tree(final_params(run), final_params(sa_reference))
    assert metrics_without_timing(run) == metrics_without_timing(sa_reference)


def test_an_fcp_actor_killed_mid_training_restarts_with_its_pool_and_finishes_with_the_same_numbers(
    tmp_path, reference, ray_session
):
    """FCP learners on two actors against the snapshots of an SP run: the pool is ray.put once and reaches every
    actor's constructor, and a restarted actor is built again with it and its learner's checkpoint; the run ends as
    the uninterrupted one trained in this process, bit for bit. (The SP-stage path, no partners given, is the same
    coordinator code, tested in tests/test_train_cli.py.)"""
    config = load_config(SMOKE, [*LONGER, "population.method=fcp", f"population.fcp.partners={reference}"])
    here = tmp_path / "fcp_reference"
    coordinator.train(config, here, ShardsHere, show_progress=False, evaluate=False)
    run = tmp_path / "fcp_killed"
    hook, killed = kill_actor_in_chunk(2, shard=1)
    summary = ray_backend.train_population(config, run, show_progress=False, evaluate=False, on_chunk=hook)
    killed.pop().join()
    assert summary["restarts"] >= 1
    manifest = RunDir(run).read_manifest()
    assert all(event["restored_update"] >= 2 for event in manifest["restart_events"])
    assert manifest["status"] == "finished" and manifest["shards"] == [[0], [1]]
    assert manifest["pool"] == RunDir(here).read_manifest()["pool"] == ["seed0@4", "seed0@8", "seed1@4", "seed1@8"]
    assert_same_tree(final_params(run), final_params(here))
    assert metrics_without_timing(run) == metrics_without_timing(here)


def test_a_worker_with_no_restarts_left_stops_resumably_and_the_resume_ends_as_uninterrupted(
    tmp_path, reference, ray_session
):
    """cluster.max_restarts=0: a killed actor is not restarted. The driver says which worker, that its restarts
    are used up and that its checkpoints are kept; the run stays "training" and a resume (with restarts) gives
    the uninterrupted run's numbers."""
    config = load_config(SMOKE, [*LONGER, "cluster.max_restarts=0"])
    run = tmp_path / "no_restarts"
    hook, killed = kill_actor_in_chunk(2)
    with pytest.raises(ray_backend.RayBackendError) as raised:
        ray_backend.train_population(config, run, show_progress=False, evaluate=False, on_chunk=hook)
    killed.pop().join()
    message = str(raised.value)
    assert message.startswith("worker for seeds [0] died and cannot be restarted (cluster.max_restarts=0 used up")
    assert "checkpoints are in the run directory" in message and raised.value.resumable
    assert RunDir(run).read_manifest()["status"] == "training"
    assert train(run, *LONGER, extra=["--no-eval", "--resume"]) == 0
    assert RunDir(run).read_manifest()["resumed_from"] >= 2
    assert_same_tree(final_params(run), final_params(reference))
    assert metrics_without_timing(run) == metrics_without_timing(reference)


def test_a_worker_killed_during_cross_play_is_restarted_and_the_matrix_is_unchanged(tmp_path, reference, ray_session):
    """The pair job of a killed cross-play worker is sent again to the restarted actor: the same matrix, the same
    episodes, and each archived episode once (the dead worker's half-written archive is replaced)."""
    run = tmp_path / "xp_killed"
    shutil.copytree(reference, run, ignore=shutil.ignore_patterns("xp", "archive", "plots", "gifs"))
    here = evaluate.evaluate_run(run, episodes=3, show_progress=False)
    here_csv, here_archive = (run / "xp" / "episodes.csv").read_text(), xp_archive(run)

    killed = []

    class KilledOnce(ray_backend.RayWorkers):
        def call(self, method, jobs):
            if method == "cross_play" and not killed:  # SIGKILL worker 0 while it plays its row
                killed.append(kill_later(self.pids()[0]))
            return super().call(method, jobs)

    workers = KilledOnce(RunDir(run).load_config(), run)
    try:
        spread = evaluate.evaluate_run(run, episodes=3, show_progress=False, workers=workers)
        killed.pop().join()
        assert workers.restarts() >= 1
    finally:
        workers.close()
    assert {k: v for k, v in here.items() if k != "wall_s"} == {k: v for k, v in spread.items() if k != "wall_s"}
    assert (run / "xp" / "episodes.csv").read_text() == here_csv
    archive = xp_archive(run)
    assert sorted(archive) == sorted(here_archive)
    for key, (ret, actions) in archive.items():
        assert ret == here_archive[key][0]
        np.testing.assert_array_equal(actions, here_archive[key][1])
    assert not list((run / "archive" / "xp").glob("*.partial"))


def test_a_killed_driver_resumes_from_the_run_directory(tmp_path, reference, ray_session, capsys):
    run = tmp_path / "driver"
    address = ray_session.get_runtime_context().gcs_address
    command = [
        sys.executable,
        "-c",
        "import sys; from cluster.cli import main; sys.exit(main(sys.argv[1:]))",
        "train",
        SMOKE,
        "--out",
        str(run),
        "--quiet",
        "--no-eval",
        "--address",
        address,
    ]
    for item in LONGER:
        command += ["--set", item]
    driver = subprocess.Popen(command, env={**os.environ, "RAY_AUTH_MODE": "disabled"}, cwd=ROOT)
    deadline = time.monotonic() + 240
    while not all(ckpt.checkpoint_path(run, s, 4).exists() for s in (0, 1)):
        assert driver.poll() is None, "the driver exited before it could be killed"
        assert time.monotonic() < deadline, "no checkpoint at update 4 within 240 s"
        time.sleep(0.05)
    driver.send_signal(signal.SIGSTOP)  # frozen mid-run, still holding the run directory's lock
    assert train(run, *LONGER, extra=["--no-eval", "--resume"]) == 2
    assert f"in use by another ocv2 process (pid {driver.pid})" in capsys.readouterr().err
    driver.send_signal(signal.SIGKILL)  # the kernel releases its lock
    driver.wait()
    assert RunDir(run).read_manifest()["status"] == "training"
    assert train(run, *LONGER, extra=["--no-eval", "--resume"]) == 0
    assert RunDir(run).read_manifest()["resumed_from"] >= 4
    assert_same_tree(final_params(run), final_params(reference))
    assert metrics_without_timing(run) == metrics_without_timing(reference)


def test_a_worker_whose_checkpoints_cannot_load_reports_that(tmp_path, reference, ray_session, capsys):
    run = tmp_path / "broken"
    shutil.copytree(reference, run)
    for update in ckpt.list_updates(run, 1):  # every checkpoint of seed 1 truncated: nothing to fall back to
        path = ckpt.checkpoint_path(run, 1, update)
        path.write_bytes(path.read_bytes()[:100])
    assert train(run, *LONGER, extra=["--no-eval", "--resume"]) == 2
    err = capsys.readouterr().err  # also the actor's "falling back" lines, forwarded by Ray
    errors = [line for line in err.splitlines() if line.startswith("ocv2 train: error:")]
    assert len(errors) == 1 and "not a readable ocv2 checkpoint" in errors[0] and "no older checkpoint" in errors[0]
    assert "max_restarts" not in err


def test_a_worker_that_cannot_start_says_why_without_resume_advice(tmp_path, reference, ray_session):
    """An actor whose constructor raised (here an FCP per_seed pool of the wrong size) died for good, and the driver
    said the worker had used up cluster.max_restarts and advised a resume that fails the same way every time."""
    config = load_config(SMOKE, [*LONGER, "population.method=fcp", f"population.fcp.partners={reference}"])
    config = dataclasses.replace(
        config,
        population=dataclasses.replace(
            config.population, fcp=dataclasses.replace(config.population.fcp, pool="per_seed", partner_seeds=1)
        ),
    )
    run = tmp_path / "run"
    run.mkdir()
    dump_config(config, run / "config.yaml")  # as RunDir.open writes it before the workers start
    workers = ray_backend.RayWorkers(config, run, pool={"w": np.zeros((3, 1, 4), np.float32)})
    try:
        with pytest.raises(ray_backend.RayBackendError) as raised:
            workers.call("position", [(0, ())])
    finally:
        workers.close()
    message = str(raised.value)
    assert message.startswith("the worker for seeds [0] could not start: ValueError: FCP per_seed pool has 3 learner")
    assert not raised.value.resumable and "max_restarts" not in message


def test_a_run_directory_the_workers_cannot_see_is_refused_by_name(tmp_path, ray_session):
    """An actor on a node without the run directory made an empty one on its own disk and trained there; the driver
    found no checkpoint only after all the training."""
    config = load_config(SMOKE, LONGER)
    absent = tmp_path / "not_shared" / "run"
    workers = ray_backend.RayWorkers(config, absent)
    try:
        with pytest.raises(RunDirError, match="the run directory is not visible on the worker's node .*shares"):
            workers.call("position", [(0, ())])
    finally:
        workers.close()
    assert not (tmp_path / "not_shared").exists()  # nothing made on the worker's disk


@ray_backend.ray.remote(num_cpus=0) if ray_backend.ray is not None else (lambda cls: cls)
class _SlowShard:
    """A shard whose chunk takes ``seconds``: long enough for a signal to land while the driver waits for it."""

    def __init__(self, seconds: float):
        self.seconds = seconds

    def advance(self, stop, _buffer, update):
        time.sleep(self.seconds)
        return AdvanceResult(stop, [], stop - update, self.seconds)


@pytest.mark.parametrize("signals", [1, 2])
def test_sigterm_while_ray_actors_train_saves_their_chunk_or_at_a_second_stops_at_once(ray_session, signals):
    """On the Ray backend SIGTERM (the command line makes it a Ctrl-C) raised a KeyboardInterrupt out of the driver's
    ray.wait, and the actors were killed with the chunk in flight; a first signal now lets the chunk finish (the
    coordinator records it, then stops), a second stops at once."""
    workers = object.__new__(ray_backend.RayWorkers)
    workers.config, workers.shards, workers.events = load_config(SMOKE), [[0], [1]], []
    workers.actors = [_SlowShard.remote(0.4), _SlowShard.remote(1.6)]  # one result returns before the signals
    jobs = [(shard, (4, None, 2)) for shard in (0, 1)]
    ray_backend.ray.get([a.advance.remote(2, None, 2) for a in workers.actors])  # both started: no start-up in the wait
    before = signal.signal(signal.SIGTERM, signal.default_int_handler)  # as the command line sets it
    # Both land after the first actor's result, while the driver waits for the second (or between the two waits).
    timers = [threading.Timer(0.8 + 0.3 * k, os.kill, (os.getpid(), signal.SIGTERM)) for k in range(signals)]
    try:
        for timer in timers:
            timer.start()
        if signals == 2:
            with pytest.raises(ChunkAbandoned):
                workers.call("advance", jobs)
        else:
            results = workers.call("advance", jobs)
            assert [(r.update, r.stop_requested) for r in results] == [(4, True), (4, True)]
    finally:
        for timer in timers:
            timer.join()
        signal.signal(signal.SIGTERM, before)
        for actor in workers.actors:
            ray_backend.ray.kill(actor)


def test_bad_cluster_input_fails_before_any_work(tmp_path, capsys, ray_session):
    assert train(tmp_path / "gpu", "cluster.num_gpus=1") == 2
    assert "cluster.num_gpus" in capsys.readouterr().err
    assert not (tmp_path / "gpu").exists()
    assert train(tmp_path / "cpu", "cluster.num_cpus=3") == 2  # 2 actors x 3 CPUs > the session's 4
    assert "cluster.num_cpus" in capsys.readouterr().err


def test_an_unreachable_address_is_a_clear_error(tmp_path, capsys, monkeypatch):
    import ray

    monkeypatch.setattr(ray, "is_initialized", lambda: False)  # as from a fresh driver
    assert train(tmp_path / "x", extra=["--address", "127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "127.0.0.1:1" in err and "cannot reach the Ray head" in err
    assert main(["train", SMOKE, "--address", "nonsense", "--quiet"]) == 2
    assert "--address" in capsys.readouterr().err
    # A study is refused the same way, and leaves no empty study directory behind (Ray starts under its lock).
    study = ROOT / "configs" / "studies" / "table1_coord_ring.yaml"
    out = tmp_path / "study"
    assert main(["study", "run", str(study), "--address", "127.0.0.1:1", "--out", str(out), "--quiet"]) == 2
    assert "cannot reach the Ray head" in capsys.readouterr().err and not out.exists()


def test_quickstart_completes_end_to_end_on_ray_with_tiny_overrides(tmp_path, ray_session):
    """The README's main job (Ray backend, the default), shrunk with --set: a 2-seed SA population with
    2 iterations; its buffers hold states of all 4 ordered pairs; cross-play, plot, GIF, archives."""
    quickstart = str(ROOT / "configs" / "quickstart.yaml")
    tiny = [
        "ppo.num_envs=4",
        "ppo.num_steps=16",
        "ppo.num_minibatches=2",
        "ppo.update_epochs=1",
        "ppo.total_timesteps=128",
        "env.max_steps=24",
        "model.conv_features=[4]",
        "model.conv_kernels=[3]",
        "model.fc_dim=8",
        "population.sa.rollouts_per_pair=1",
        "eval.episodes=2",
        "eval.gifs=1",
        "run.checkpoint_every=1",
    ]
    args = ["train", quickstart, "--out", str(tmp_path / "qs"), "--quiet"]
    for item in tiny:
        args += ["--set", item]
    assert main(args) == 0
    run = tmp_path / "qs"
    assert RunDir(run).read_manifest()["status"] == "finished"
    assert sorted(p.name for p in (run / "sa").iterdir()) == ["buffer_000.msgpack", "buffer_001.msgpack"]
    import json

    summary = json.loads((run / "xp" / "summary.json").read_text())
    assert summary["num_policies"] == 2 and summary["episodes_per_pair"] == 2
    assert (run / "plots" / "training.png").stat().st_size > 0
    assert [p.name for p in (run / "gifs").iterdir()] == ["seed_0_selfplay.gif"]
    assert sorted(xp_archive(run)) == [(i, j, e) for i in (0, 1) for j in (0, 1) for e in (0, 1)]
    with ArchiveReader(run / "archive" / "xp" / "seat0_seed_0.mcap") as reader:
        episode = reader.episode(0)
        assert episode.actions.shape == (24, 2) and episode.meta["layout"] == "cramped_room"
    rows = RunDir(run).read_metrics()  # each (seed, update) exactly once, though two actors reported
    assert sorted((int(r["seed"]), int(r["update"])) for r in rows) == [(s, u) for s in (0, 1) for u in (1, 2)]

    config = RunDir(run).load_config()
    trainer = ppo.make_trainer(config)
    template = runstate.state_template(trainer, 0)
    for iteration, update in enumerate((0, 1)):
        # Rebuilt here in one process from the checkpointed policies: the Ray buffer is exactly this.
        params = jax.tree.map(
            lambda *xs: np.stack(xs),
            *(
                ckpt.load(ckpt.checkpoint_path(run, s, update), template, config.fingerprint())[1].params
                for s in (0, 1)
            ),
        )
        key = derive_key(config.population.seed, "sa", iteration)
        expected = collect_buffer(trainer.network.apply, 0, ppo.eval_env(config), params, key, config.population.sa)
        meta, stored = ckpt.load(run / "sa" / f"buffer_{iteration:03d}.msgpack", expected, config.fingerprint())
        assert meta["states"] == 4 * 1 * 2  # 4 ordered pairs x 1 rollout x 24 // 10 kept states
        assert_same_tree(stored, expected)
        # Every collection episode is archived: all 4 ordered pairs.
        with ArchiveReader(run / "archive" / "sa" / f"iteration_{iteration:03d}.mcap") as reader:
            assert sorted(tuple(m["seeds"]) for m in reader.episodes()) == [(0, 0), (0, 1), (1, 0), (1, 1)]
            assert {m["iteration"] for m in reader.episodes()} == {iteration}


def test_starting_ray_after_jax_says_one_line_of_its_own_and_no_alarms(tmp_path):
    # A driver where JAX already runs (a notebook, `ocv2 xp` after loading policies) starting Ray with
    # the auth mode unset: no JAX fork warning for Ray's process launches, no Ray token-auth notice; and the
    # command line's SIGTERM handler is still in place after Ray started.
    code = (
        "import logging, jax, ray\n"
        "jax.numpy.zeros(1).block_until_ready()\n"
        "logging.basicConfig(level=logging.WARNING, format='%(name)s: %(message)s')\n"
        "logging.getLogger('cluster').setLevel(logging.INFO)\n"
        "from cluster.runtime.ray_backend import connect\n"
        "from population.config import ClusterConfig\n"
        "import signal\n"
        "signal.signal(signal.SIGTERM, signal.default_int_handler)\n"  # as the command line sets it
        "assert connect(ClusterConfig(local_cpus=1))\n"
        # SIGTERM still stops the command as Ctrl-C does (its chunk saved), not through Ray's sys.exit(15)
        "assert signal.getsignal(signal.SIGTERM) is signal.default_int_handler, signal.getsignal(signal.SIGTERM)\n"
        "ray.shutdown()\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_AUTH_MODE", "RAY_ADDRESS")}
    env.update(PYTHONPATH=str(Path(__file__).resolve().parents[1]), HOME=str(tmp_path))  # Ray's token file there
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "os.fork()" not in done.stderr and "Token authentication is enabled" not in done.stderr, done.stderr
    ours = [line for line in done.stderr.splitlines() if line.startswith("cluster.runtime.ray_backend:")]
    assert len(ours) == 1 and "token authentication" in ours[0] and "RAY_AUTH_MODE=disabled" in ours[0]
