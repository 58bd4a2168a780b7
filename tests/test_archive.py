"""The MCAP trajectory archive (cluster/archive/, population/record.py, ``ocv2 archive``)."""

from __future__ import annotations

import base64
import builtins
import errno
import io
import json
import os
import pickle
import shutil
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("mcap", reason="the archive is MCAP: needs mcap (pip install mcap)")

from mcap.reader import make_reader
from mcap.writer import Writer
from PIL import Image

import ocv2
from cluster.archive import (
    ArchiveError,
    ArchiveReader,
    ArchiveWriter,
    record_episodes,
    record_pairs,
    recover,
    states_as_buffer,
)
from cluster.cli import main
from cluster.cli.play import _writer as play_writer
from ocv2 import dynamics
from ocv2.render import render_frames
from population.evaluation import play_episodes
from population.record import jitted_play_recorded

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 30
EPISODES = 3
KEY = jax.random.PRNGKey(0)  # episode 1 earns shaped reward
META = {"method": "xp", "iteration": 2, "policies": ["sp_0", "sp_1"], "checkpoints": ["c0", "c1"], "seed": 7}


def _apply(params, hidden, obs, reset):
    """A scripted policy: fixed logits (the params), no memory."""
    batch = obs.shape[1]
    return hidden, jnp.broadcast_to(params, (1, batch, params.shape[0])), jnp.zeros((1, batch))


PARAMS = (jnp.zeros(6), jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 2.0]))  # seat 0 uniform, seat 1 likes 'interact'


@pytest.fixture(scope="module")
def env():
    return ocv2.make("cramped_room", max_steps=STEPS)


@pytest.fixture(scope="module")
def recorded(env):
    return jax.device_get(jitted_play_recorded(_apply, 4, env, EPISODES)(PARAMS, KEY))


@pytest.fixture(scope="module")
def archive(tmp_path_factory, env, recorded):
    path = str(tmp_path_factory.mktemp("archive") / "xp.mcap")
    with ArchiveWriter(path) as writer:
        indices = record_episodes(writer, env, recorded, META)
    assert indices == [0, 1, 2]
    return path


def _episode(recorded, e):
    return (
        jax.tree.map(lambda x: x[e], recorded.states),
        recorded.actions[e],
        recorded.rewards[e],
        recorded.shaped_rewards[e],
        recorded.dones[e],
    )


def _assert_same_episode(got, recorded, e):
    states, actions, rewards, shaped, dones = _episode(recorded, e)
    for name, a, b in [
        ("actions", got.actions, actions),
        ("rewards", got.rewards, rewards),
        ("shaped", got.shaped_rewards, shaped),
        ("dones", got.dones, dones),
    ]:
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
    for a, b in zip(jax.tree.leaves(got.states), jax.tree.leaves(states)):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


def test_recorded_episodes_are_play_episodes(env, recorded):
    """Same key, same episodes as the evaluation rollout (returns and every state)."""
    assert recorded.actions.shape == (EPISODES, STEPS, 2) and recorded.actions.dtype == np.int32
    assert recorded.dones[:, -1].all() and recorded.dones.sum() == EPISODES
    assert jax.tree.leaves(recorded.states)[0].shape[:2] == (EPISODES, STEPS + 1)
    played = play_episodes(_apply, 4, env, PARAMS, KEY, EPISODES, keep_every=1)
    np.testing.assert_array_equal(recorded.returns, np.asarray(played.returns))
    for a, b in zip(jax.tree.leaves(recorded.states), jax.tree.leaves(played.states)):
        np.testing.assert_array_equal(a[:, :STEPS], np.asarray(b))
    np.testing.assert_array_equal(recorded.returns, recorded.rewards.sum(axis=1))
    assert (recorded.shaped_rewards != 0).any()  # the data is not trivially zero
    # The last state is the episode's terminal one (not the auto-reset state that follows it), and every
    # state is the transition of the one before it under the recorded actions.
    assert (recorded.states.step[:, -1] == STEPS).all() and recorded.states.done[:, -1].all()
    transition = jax.jit(lambda s, a: dynamics.transition(env.config, jax.random.PRNGKey(0), s, a).state)
    for e in range(EPISODES):
        for t in (0, STEPS // 2, STEPS - 1):
            state = jax.tree.map(lambda x: x[e, t], recorded.states)
            following = transition(state, jnp.asarray(recorded.actions[e, t]))
            for a, b in zip(jax.tree.leaves(following), jax.tree.leaves(recorded.states), strict=True):
                np.testing.assert_array_equal(np.asarray(a), b[e, t + 1])


def test_round_trip(archive, recorded):
    reader = ArchiveReader(archive)
    assert reader.finished and len(reader) == EPISODES and not os.path.exists(archive + ".partial")
    metas = reader.episodes()
    for e, meta in enumerate(metas):
        assert {k: meta[k] for k in META} == META
        assert meta["episode"] == e and meta["pair_episode"] == e and meta["layout"] == "cramped_room"
        assert meta["steps"] == STEPS and meta["num_agents"] == 2
        assert meta["env_params"]["max_steps"] == STEPS
        assert meta["return"] == pytest.approx(float(recorded.returns[e]))
        assert meta["shaped_return"] == pytest.approx(recorded.shaped_rewards[e].sum(axis=0).tolist())
        got = reader.episode(e)
        assert got.meta == meta
        _assert_same_episode(got, recorded, e)
    assert reader.episode(-1).meta["episode"] == EPISODES - 1
    for e, got in enumerate(reader.iter_episodes()):
        _assert_same_episode(got, recorded, e)
    assert reader.layout(0) is ocv2.LAYOUTS["cramped_room"]


def test_record_pairs_writes_every_pair(tmp_path, env):
    params_a = jnp.stack([PARAMS[0], PARAMS[1]])
    params_b = jnp.stack([PARAMS[1], PARAMS[0]])
    keys = jnp.stack([KEY, jax.random.PRNGKey(4)])
    path = tmp_path / "pairs.mcap"
    with ArchiveWriter(path) as writer:
        indices = record_pairs(
            writer, _apply, 4, env, params_a, params_b, keys, 1, [{"policies": [0, 1]}, {"policies": [1, 0]}]
        )
    assert indices == [0, 1]
    metas = ArchiveReader(path).episodes()
    assert [m["policies"] for m in metas] == [[0, 1], [1, 0]]
    played = play_episodes(_apply, 4, env, PARAMS, KEY, 1)
    assert metas[0]["return"] == pytest.approx(float(played.returns[0]))


_KILLED_WRITER = textwrap.dedent("""
    import os, pickle, signal, sys
    import jax
    from cluster.archive import ArchiveWriter
    recorded, path = pickle.load(open(sys.argv[1], "rb"))
    writer = ArchiveWriter(path, foxglove_frames=True, frame_tile_size=8, chunk_size=512).open()
    def episode(e):
        states = jax.tree.map(lambda x: x[e], recorded.states)
        writer.write_episode({"seed": e}, states, recorded.actions[e], recorded.rewards[e],
                             recorded.shaped_rewards[e], recorded.dones[e], layout="cramped_room")
    episode(0)
    episode(1)
    mcap_writer = writer._out.mcap
    add_message = mcap_writer.add_message
    count = [0]
    def dying(*args, **kwargs):
        count[0] += 1
        if count[0] == 25:  # in the middle of episode 2: killed for real, no cleanup at all
            os.kill(os.getpid(), signal.SIGKILL)
        return add_message(*args, **kwargs)
    mcap_writer.add_message = dying
    episode(2)
    print("not reached")
""")


def test_killed_writer_is_recovered(tmp_path, recorded, capsys):
    path = str(tmp_path / "run.mcap")
    data = tmp_path / "recorded.pkl"
    data.write_bytes(pickle.dumps((recorded, path)))
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": REPO}
    child = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(data)],
        env=env,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert child.returncode == -9, child.stderr
    assert not os.path.exists(path) and os.path.getsize(path + ".partial") > 0

    partial = ArchiveReader(path + ".partial")  # readable as it is, without its summary
    summary = partial.info()
    assert not summary["finished"] and summary["episodes"] == 2
    assert summary["uncommitted_messages"] > 0  # part of episode 2 reached the disk and is ignored
    with pytest.raises(ArchiveError, match=r"\.partial' is unfinished .*ocv2 archive recover"):
        states_as_buffer(path + ".partial")  # an SA reset buffer (population.sa.archives) takes no half file

    assert main(["archive", "recover", path + ".partial"]) == 0
    out = capsys.readouterr().out
    assert "recovered 2 complete episode(s)" in out and path in out and "dropped" in out
    fixed = ArchiveReader(path)
    assert fixed.finished and len(fixed) == 2 and fixed.info()["uncommitted_messages"] == 0
    for e in range(2):
        got = fixed.episode(e)
        assert got.meta["seed"] == e
        _assert_same_episode(got, recorded, e)
        assert fixed.frames(e).shape == (STEPS + 1, 4 * 8, 5 * 8, 3)
    assert int(states_as_buffer(path, keep_every=1).step.shape[0]) == 2 * STEPS  # the recovered file: both episodes

    report = recover(path + ".partial", tmp_path / "again.mcap")
    assert (report.episodes, report.transitions, report.source_finished) == (2, 2 * STEPS, False)
    assert report.dropped_messages > 0 and report.tail_error
    assert main(["archive", "recover", path + ".partial"]) == 2  # the default --out exists now
    assert "already exists" in capsys.readouterr().err


def test_an_exception_inside_with_keeps_the_episodes_unfinished_and_an_old_file_whole(tmp_path, recorded):
    """Leaving the block by an exception (Ctrl-C during a cross-play's re-evaluation) once finished the file: a
    re-evaluation interrupted after one episode replaced a whole archive by a "finished" one holding part of
    what was meant, beside a matrix.csv that described the old one. Now the episodes stay in the .partial
    (recoverable) and the old file is not touched."""
    path = tmp_path / "a.mcap"
    states, actions, _, _, dones = _episode(recorded, 0)
    rng = np.random.default_rng(0)  # arbitrary floats survive exactly
    rewards, shaped = rng.normal(size=STEPS).astype(np.float32), rng.normal(size=(STEPS, 2)).astype(np.float32)
    with pytest.raises(RuntimeError):
        with ArchiveWriter(path) as writer:
            writer.write_episode(META, states, actions, rewards, shaped, dones, layout="cramped_room")
            raise RuntimeError("boom")
    assert not path.exists()
    report = recover(str(path) + ".partial", str(path))
    reader = ArchiveReader(path)
    assert reader.finished and len(reader) == 1 and report is not None
    got = reader.episode(0)
    assert np.array_equal(got.rewards, rewards) and np.array_equal(got.shaped_rewards, shaped)
    assert got.meta["return"] == pytest.approx(float(rewards.sum(dtype=np.float64)))
    with pytest.raises(ArchiveError, match="already exists"):
        ArchiveWriter(path).open()
    whole = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with ArchiveWriter(path, overwrite=True) as writer:  # a re-evaluation, interrupted after one episode
            writer.write_episode(META, states, actions, rewards, shaped, dones, layout="cramped_room")
            raise KeyboardInterrupt
    assert path.read_bytes() == whole
    with ArchiveWriter(path, overwrite=True) as writer:  # the next one finishes, and replaces it
        writer.write_episode(META, states, actions, rewards, shaped, dones, layout="cramped_room")
        writer.write_episode(META, states, actions, rewards, shaped, dones, layout="cramped_room")
    assert len(ArchiveReader(path)) == 2 and not os.path.exists(str(path) + ".partial")
    with pytest.raises(KeyboardInterrupt):
        with ArchiveWriter(tmp_path / "b.mcap"):  # interrupted before its first episode (a compile)
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap"]  # no header-only .partial left


def test_ctrl_c_in_the_first_episode_leaves_no_header_only_file(tmp_path, recorded):
    """Nothing to recover, and a later writer (``ocv2 play --out`` the same path) would refuse it as unfinished."""
    path = str(tmp_path / "first.mcap")
    with pytest.raises(KeyboardInterrupt), ArchiveWriter(path) as writer:
        real, calls = writer._out.mcap.add_message, []

        def interrupted(*args, **kwargs):
            calls.append(1)
            if len(calls) == 5:  # inside the first episode's step messages
                raise KeyboardInterrupt
            return real(*args, **kwargs)

        writer._out.mcap.add_message = interrupted
        writer.write_episode({}, *_episode(recorded, 0), layout="cramped_room")
    assert not os.path.exists(path) and not os.path.exists(path + ".partial")
    with ArchiveWriter(path) as writer:  # the same path again, as a rerun would
        writer.write_episode({}, *_episode(recorded, 0), layout="cramped_room")
    assert len(ArchiveReader(path)) == 1


def test_a_finished_archive_s_rename_is_made_durable(tmp_path, recorded, monkeypatch):
    """The folder is fsynced after the rename: an SA buffer saved after its archive must not outlive it."""
    import cluster.archive.writer as writer_module

    synced = []
    monkeypatch.setattr(writer_module, "fsync_folder", lambda folder: synced.append((folder, os.listdir(folder))))
    path = tmp_path / "durable.mcap"
    with ArchiveWriter(str(path)) as writer:
        writer.write_episode({}, *_episode(recorded, 0), layout="cramped_room")
    assert synced == [(str(tmp_path), ["durable.mcap"])]  # after the rename, of the folder that holds it


def test_write_episode_rejects_bad_input(tmp_path, recorded):
    states, actions, rewards, shaped, dones = _episode(recorded, 0)
    with ArchiveWriter(tmp_path / "bad.mcap") as writer:
        with pytest.raises(ValueError, match="T \\+ 1"):
            writer.write_episode(
                {}, jax.tree.map(lambda x: x[:-1], states), actions, rewards, shaped, dones, layout="cramped_room"
            )
        with pytest.raises(ValueError, match="reserved"):
            writer.write_episode({"steps": 3}, states, actions, rewards, shaped, dones, layout="cramped_room")
        with pytest.raises(ValueError, match="not layout 'asymm_advantages'"):
            writer.write_episode({}, states, actions, rewards, shaped, dones, layout="asymm_advantages")
        with pytest.raises(ValueError, match="needs the layout"):
            writer.write_episode({}, states, actions, rewards, shaped, dones)
        with pytest.raises(TypeError, match="JSON"):
            writer.write_episode({"f": object()}, states, actions, rewards, shaped, dones, layout="cramped_room")
        deep: list = []
        for _ in range(40):  # deeper than a reader accepts: never written
            deep = [deep]
        with pytest.raises(ArchiveError, match="nests deeper than 32 levels"):
            writer.write_episode({"deep": deep}, states, actions, rewards, shaped, dones, layout="cramped_room")
    assert len(ArchiveReader(tmp_path / "bad.mcap")) == 0


def test_replay_to_gif(archive, recorded, tmp_path, capsys):
    out = tmp_path / "ep1.gif"
    assert main(["archive", "replay", archive, "--episode", "1", "--out", str(out), "--tile-size", "8"]) == 0
    assert f"{STEPS + 1} frames" in capsys.readouterr().out
    with Image.open(out) as gif:
        assert gif.n_frames == STEPS + 1 and gif.size == (5 * 8, 4 * 8)
        frames = []
        for index in range(gif.n_frames):
            gif.seek(index)
            frames.append(np.asarray(gif.convert("RGB")))

    # The frames are episode 1's, not another's: the GIF's palette may move a few pixels, another episode most
    def off(e: int) -> float:
        expected = render_frames(jax.tree.map(lambda x: x[e], recorded.states), "cramped_room", tile_size=8)
        return float(np.mean(np.any(np.stack(frames) != expected, axis=-1)))

    assert off(1) < 0.005 < min(off(0), off(2)), [off(e) for e in range(EPISODES)]


def test_replay_checks_the_frame_size_and_never_replaces_a_file_unless_forced(archive, tmp_path, capsys):
    """--tile-size 9999 once drew 20 GB of frames until the kernel killed it; a GIF there was written over."""
    out = tmp_path / "ep.gif"
    assert main(["archive", "replay", archive, "--out", str(out), "--tile-size", "9999"]) == 2
    assert "the tile size for cramped_room is at most" in capsys.readouterr().err and not out.exists()
    out.write_text("precious")
    assert main(["archive", "replay", archive, "--out", str(out), "--tile-size", "8"]) == 2
    assert "exists; pass --force to replace it" in capsys.readouterr().err and out.read_text() == "precious"
    assert main(["archive", "replay", archive, "--out", str(out), "--tile-size", "8", "--force"]) == 0
    (tmp_path / "file").write_text("x")
    assert main(["archive", "recover", archive, "--out", str(tmp_path / "file" / "x.mcap")]) == 2
    assert "lies under" in capsys.readouterr().err


def test_archive_as_sa_buffer(archive, recorded, env):
    buffer = states_as_buffer(archive, keep_every=10)
    kept = list(range(0, STEPS, 10))
    assert buffer.step.shape == (EPISODES * len(kept),)
    expected = jax.tree.map(lambda x: x[:, kept].reshape((-1,) + x.shape[2:]), recorded.states)
    for a, b in zip(jax.tree.leaves(buffer), jax.tree.leaves(expected)):
        np.testing.assert_array_equal(np.asarray(a), b)
    reset = jax.jit(env.reset_state)
    for seed in range(4):
        key = jax.random.PRNGKey(seed)
        state = reset(key, buffer)
        index = int(jax.random.randint(key, (), 0, buffer.step.shape[0]))  # the env's own draw
        assert int(state.step) == 0 and not bool(state.done)
        np.testing.assert_array_equal(state.grid, buffer.grid[index])
        np.testing.assert_array_equal(state.agents.x, buffer.agents.x[index])
        np.testing.assert_array_equal(state.recipe, buffer.recipe[index])
    ocv2.make("cramped_room", max_steps=STEPS, initial_state_buffer=buffer)  # validates as an SA buffer
    with pytest.raises(ArchiveError, match="not 'asymm_advantages'"):
        states_as_buffer(archive, layout="asymm_advantages")


def test_archive_as_sa_buffer_keeps_the_states_collection_keeps_when_k_does_not_divide_t(tmp_path):
    """T = 30, k = 7: SA collection keeps t = 0, 7, 14, 21 (t < 28) of each episode; the buffer read back from its
    archive must hold the same states (it also took t = 28)."""
    from population.config.schema import SAConfig
    from population.sa import collect_pairs

    def apply(params, hidden, obs, reset):  # a fixed policy: the logits are the parameters
        batch = obs.shape[1]
        return hidden, jnp.broadcast_to(params, (1, batch, params.shape[0])), jnp.zeros((1, batch))

    env = ocv2.make("cramped_room", max_steps=30)
    params = jnp.stack([jnp.zeros(6), jnp.array([0.0, 0, 0, 0, 0, 2.0])])
    sa = SAConfig(rollouts_per_pair=2, keep_every=7)
    part, record = collect_pairs(apply, 4, env, params, jax.random.PRNGKey(1), sa, pairs=[(0, 1)], record=True)
    path = tmp_path / "sa.mcap"
    with ArchiveWriter(path) as writer:
        record_episodes(writer, env, jax.tree.map(lambda x: np.asarray(x[0]), record), {"method": "sa"})
    buffer = states_as_buffer(path, keep_every=7)
    assert np.asarray(buffer.step).tolist() == [0, 7, 14, 21] * 2
    for a, b in zip(jax.tree.leaves(buffer), jax.tree.leaves(part.states), strict=True):  # part: [pairs, states]
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[0])


def test_an_episode_shorter_than_keep_every_is_named_not_silently_dropped(archive):
    with pytest.raises(ArchiveError, match=r"episode 0 has 30 steps, fewer than keep_every=31: SA collection would"):
        states_as_buffer(archive, keep_every=31)


def test_buffer_rejects_mixed_layouts(tmp_path, archive):
    other = ocv2.make("asymm_advantages", max_steps=2)
    state = other.reset_state(jax.random.PRNGKey(0))
    states = jax.tree.map(lambda x: jnp.stack([x] * 3), state)
    path = tmp_path / "mixed.mcap"
    with ArchiveWriter(path) as writer:
        writer.write_episode(
            {},
            states,
            np.zeros((2, 2), np.int32),
            np.zeros(2, np.float32),
            np.zeros((2, 2), np.float32),
            np.array([False, True]),
            layout="asymm_advantages",
        )
    assert states_as_buffer(path, keep_every=1).grid.shape == (2, 5, 9, 3)
    with pytest.raises(ArchiveError, match="one kitchen"):
        states_as_buffer([path, archive], keep_every=1)


def test_info_lists_episodes_layouts_returns(archive, recorded, capsys):
    assert main(["archive", "info", archive]) == 0
    out = capsys.readouterr().out
    assert "finished ocv2 archive, 3 complete episode(s), 90 transitions" in out
    assert "layouts: cramped_room (3)" in out and "policies: sp_0 + sp_1 (3)" in out and "methods: xp (3)" in out
    assert f"mean {recorded.returns.mean():.2f}" in out
    rows = [line.split() for line in out.splitlines() if line.split()[:1] in (["0"], ["1"], ["2"])]
    assert [r[:3] for r in rows] == [[str(e), "cramped_room", str(STEPS)] for e in range(EPISODES)]
    assert main(["archive", "info", archive, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["summary"]["episodes"] == 3 and data["summary"]["layouts"] == {"cramped_room": 3}
    assert [m["episode"] for m in data["episodes"]] == [0, 1, 2]


def test_bad_input_is_a_clear_error(tmp_path, archive, capsys):
    text = tmp_path / "notes.mcap"
    text.write_text("not an archive\n")
    cases = [
        (["archive", "info", str(text)], "not an MCAP file"),
        (["archive", "info", str(tmp_path / "missing.mcap")], "no such file"),
        (
            ["archive", "replay", archive, "--episode", "3", "--out", str(tmp_path / "x.gif")],
            "has no episode 3; its complete episodes are 0..2",
        ),
        (["archive", "replay", archive, "--out", str(tmp_path / "x.png")], ".gif"),
        (["archive", "recover", str(text), "--out", str(tmp_path / "fixed.mcap")], "not an MCAP file"),
        (["archive", "recover", archive, "--out", archive], "already exists"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
    assert not (tmp_path / "fixed.mcap").exists() and not (tmp_path / "x.gif").exists()
    assert main(["archive"]) == 2  # no action: argparse usage


def test_a_file_without_a_header_is_no_archive_and_nothing_to_recover(tmp_path, capsys):
    """Past what a writer killed inside its header can leave, a file with no header is not an ocv2 archive (it was
    reported as an unfinished one, and recover made a "finished" archive of it); an empty one has nothing to recover."""
    garbage, empty = tmp_path / "garbage.mcap", tmp_path / "empty.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + np.random.default_rng(0).bytes(3000))
    empty.write_bytes(b"")
    assert main(["archive", "info", str(garbage)]) == 2
    assert "is not an ocv2 archive: no readable header record in its 3008 bytes" in capsys.readouterr().err
    assert main(["archive", "recover", str(garbage), "--out", str(tmp_path / "g.mcap")]) == 2
    capsys.readouterr()
    assert main(["archive", "recover", str(empty), "--out", str(tmp_path / "e.mcap")]) == 2
    assert "nothing to recover (empty file" in capsys.readouterr().err
    # info once called the empty file an UNFINISHED archive and advised `archive recover`, exit 0
    assert main(["archive", "info", str(empty)]) == 2
    assert f"{empty}: no ocv2 header in its 0 bytes" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.mcap", "garbage.mcap"]


def test_a_pipe_or_device_is_no_archive(tmp_path, capsys):
    """/dev/null read as an empty (UNFINISHED) archive, and a named pipe blocked the read until a writer came."""
    pipe = tmp_path / "pipe.mcap"
    os.mkfifo(pipe)
    for path in (str(pipe), os.devnull):
        assert main(["archive", "info", path]) == 2
        assert f"{path!r} is not a regular file (a pipe, socket or device)" in capsys.readouterr().err


def test_a_file_with_no_complete_episode_is_refused_and_no_archive_is_written(tmp_path, archive, capsys):
    """A file cut inside its first episode, or a finished one that holds none, has nothing to recover: an empty
    "finished" archive would read as a result."""
    cut = tmp_path / "cut.mcap.partial"
    with open(archive, "rb") as source:
        cut.write_bytes(source.read(400))  # the header and the channel records, then part of the first chunk
    empty = tmp_path / "none.mcap"
    with ArchiveWriter(str(empty)):
        pass
    for path in (cut, empty):
        out = tmp_path / "fixed.mcap"
        with pytest.raises(ArchiveError, match=rf"{path}': no complete episode to recover"):
            recover(str(path), str(out))
        assert main(["archive", "recover", str(path), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert "no complete episode to recover" in err and len(err.splitlines()) == 1
        assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.mcap.partial", "none.mcap"]
    assert main(["archive", "recover", str(cut)]) == 2  # the default --out, cut.mcap, is not written either
    assert not (tmp_path / "cut.mcap").exists()


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_is_never_decompressed_past_the_size_its_header_claims(compression):
    """A frame may state its own (larger) content size, which mcap's reader believes: 1 MiB of zeros behind a
    claim of 100 bytes is refused after 101 bytes, not decompressed whole (the same ratio asks gigabytes of a
    20 KB file)."""
    import lz4.frame
    import zstandard
    from mcap.records import Chunk

    from cluster.archive.reader import _decompressed

    def chunk(plain: bytes, claimed: int) -> Chunk:
        compress = zstandard.ZstdCompressor().compress if compression == "zstd" else lz4.frame.compress
        return Chunk(
            message_start_time=0,
            message_end_time=0,
            uncompressed_size=claimed,
            uncompressed_crc=0,
            compression=compression,
            data=compress(plain),
        )

    assert _decompressed(chunk(b"\0" * (1 << 20), 100)) is None
    assert _decompressed(chunk(b"records", 100)) is None  # fewer bytes than claimed: damaged too
    assert _decompressed(chunk(b"records", 7)) == b"records"


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_reading_a_crafted_chunk_allocates_what_it_claims_not_what_it_holds(tmp_path, compression, capsys):
    """Through the reader, on every path a refused chunk takes (the scan, then the warning that describes it):
    64 MiB of zeros behind a claim of 100 bytes never become 64 MiB in memory."""
    import tracemalloc

    import lz4.frame
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, Header

    compress = zstandard.ZstdCompressor().compress if compression == "zstd" else lz4.frame.compress
    builder = RecordBuilder()
    Header(profile="ocv2-archive", library="crafted").write(builder)
    Chunk(
        message_start_time=0,
        message_end_time=0,
        uncompressed_size=100,
        uncompressed_crc=0,
        compression=compression,
        data=compress(bytes(64 << 20)),
    ).write(builder)
    path = tmp_path / "bomb.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + builder.end())
    tracemalloc.start()
    try:
        reader = ArchiveReader(str(path))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, f"{peak / 2**20:.0f} MiB"
    assert len(reader) == 0 and any("does not decompress to the 100 bytes it claims" in w for w in reader.warnings)


def test_foxglove_channel_only_when_enabled(tmp_path, archive, recorded):
    from mcap.reader import make_reader  # an independent reader: the file is standard MCAP

    plain = ArchiveReader(archive)
    assert "frames" not in plain.topics() and not plain.info()["foxglove_frames"]
    with pytest.raises(ArchiveError, match="foxglove_frames"):
        plain.frames(0)

    path = tmp_path / "fox.mcap"
    with ArchiveWriter(path, foxglove_frames=True, frame_tile_size=8) as writer:
        writer.write_episode(META, *_episode(recorded, 0), layout="cramped_room")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == 2 * (STEPS + 1) + 1
        images = []
        for schema, channel, message in reader.iter_messages(topics=["frames"]):
            assert schema.name == "foxglove.RawImage" and schema.encoding == "jsonschema"
            assert channel.message_encoding == "json"
            image = json.loads(message.data)
            assert set(image) == {"timestamp", "frame_id", "width", "height", "encoding", "step", "data"}
            assert image["encoding"] == "rgb8" and image["step"] == image["width"] * 3
            assert image["timestamp"]["sec"] * 10**9 + image["timestamp"]["nsec"] == message.log_time
            pixels = base64.b64decode(image["data"])
            images.append(np.frombuffer(pixels, np.uint8).reshape(image["height"], image["width"], 3))
        fields = json.loads(next(s for s in summary.schemas.values() if s.name == "foxglove.RawImage").data)
        assert set(fields["properties"]) >= {"timestamp", "frame_id", "width", "height", "encoding", "step", "data"}
    assert len(images) == STEPS + 1 and images[0].shape == (4 * 8, 5 * 8, 3)
    expected = render_frames(jax.tree.map(lambda x: x[0], recorded.states), "cramped_room", tile_size=8)
    np.testing.assert_array_equal(np.stack(images), expected)
    np.testing.assert_array_equal(ArchiveReader(path).frames(0), expected)


# ---------------------------------------------------------------------------------------------------
# Faults: full disks, corrupt chunks, crafted records
# ---------------------------------------------------------------------------------------------------


class _FullDisk(io.FileIO):
    """A file on a disk that fills up after ``budget[0]`` more bytes (the last write is torn)."""

    def __init__(self, path, mode, budget):
        super().__init__(path, mode)
        self.budget = budget

    def write(self, data):
        if len(data) > self.budget[0]:
            if self.budget[0]:
                super().write(bytes(data)[: self.budget[0]])
            self.budget[0] = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.budget[0] -= len(data)
        return super().write(data)


def _open_on_full_disk(monkeypatch, writer, budget):
    """Open ``writer`` with its ``.partial`` on a disk that has ``budget[0]`` bytes left."""
    real_open = builtins.open

    def fake_open(file, mode="r", *args, **kwargs):
        if str(file).endswith(".partial") and mode == "wb":
            return io.BufferedWriter(_FullDisk(file, mode, budget))
        return real_open(file, mode, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(builtins, "open", fake_open)
        return writer.open()


@pytest.mark.parametrize("fault", ["ENOSPC", "fsync EIO"])
def test_write_error_fails_the_writer_and_keeps_earlier_episodes(tmp_path, recorded, monkeypatch, fault, capsys):
    """A full disk (or a failed fsync) mid-episode: the caller sees the error, later episodes are
    refused, and every episode completed before it stays readable and recoverable."""
    path = str(tmp_path / "full.mcap")
    budget = [1 << 30]
    writer = _open_on_full_disk(monkeypatch, ArchiveWriter(path, fsync=True), budget)
    try:
        assert writer.write_episode(META, *_episode(recorded, 0), layout="cramped_room") == 0
        if fault == "ENOSPC":
            budget[0] = 100  # the disk fills up inside episode 1's chunk
        else:

            def failing_fsync(fd):
                raise OSError(errno.EIO, "Input/output error")

            monkeypatch.setattr(os, "fsync", failing_fsync)
        with pytest.raises(OSError) as raised:
            writer.write_episode(META, *_episode(recorded, 1), layout="cramped_room")
    finally:
        monkeypatch.undo()
        writer.close()  # as a with block would: a failed writer is left unfinished
    assert raised.value.errno == (errno.ENOSPC if fault == "ENOSPC" else errno.EIO)
    assert writer.failed is raised.value
    with pytest.raises(ArchiveError, match="failed earlier.*1 episode.*ocv2 archive recover"):
        writer.write_episode(META, *_episode(recorded, 2), layout="cramped_room")
    assert not os.path.exists(path)  # never renamed: an unfinished archive is not passed off as whole

    partial = ArchiveReader(path + ".partial")
    assert len(partial) == 1 and not partial.finished and partial.warnings == []
    assert partial.info()["uncommitted_messages"] == 0  # cut back to the last complete episode
    _assert_same_episode(partial.episode(0), recorded, 0)
    assert main(["archive", "recover", path + ".partial"]) == 0
    assert "recovered 1 complete episode(s)" in capsys.readouterr().out
    _assert_same_episode(ArchiveReader(path).episode(0), recorded, 0)


def test_a_disk_full_at_opening_leaves_no_file(tmp_path, monkeypatch):
    path = tmp_path / "none.mcap"
    with pytest.raises(OSError, match="No space left"):
        _open_on_full_disk(monkeypatch, ArchiveWriter(path), [0])
    assert os.listdir(tmp_path) == []  # not even an empty .partial that looks like a killed writer's


def test_play_archives_fsync_every_episode(tmp_path, recorded, monkeypatch):
    """A human's episode is on disk (fsynced) once written, not only at the end of the session."""
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    writer, path = play_writer(str(tmp_path / "play.mcap"), "cramped_room", 5.0)
    try:
        writer.write_episode({}, *_episode(recorded, 0), layout="cramped_room")
        assert synced, "the play archive was not fsynced at the episode's end"
    finally:
        writer.close()
    assert len(ArchiveReader(path)) == 1


def _chunks(path) -> list:
    with open(path, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


def _damage(path, offset, data: bytes):
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(data)


@pytest.mark.parametrize(
    "where",
    [
        "data of chunk 1",
        "data of chunk 0 (holds the channels)",
        "data of chunk 0 of an unfinished file",
        "length of chunk 1",
    ],
)
def test_corrupt_chunk_is_skipped(tmp_path, archive, recorded, where, capsys):
    """One bad chunk costs its own episode only: info, recover and replay keep every later episode."""
    path = str(tmp_path / "damaged.mcap")
    shutil.copyfile(archive, path)
    chunks = _chunks(path)
    assert len(chunks) == EPISODES  # one chunk per episode (a chunk ends at every episode end)
    bad = 0 if "chunk 0" in where else 1
    chunk = chunks[bad]
    if where.startswith("data"):  # flip bytes in the middle of the compressed data
        middle = chunk.chunk_start_offset + chunk.chunk_length // 2
        _damage(path, middle, bytes(b ^ 0xFF for b in open(path, "rb").read()[middle : middle + 16]))
    else:  # the record's length field: the records after it no longer line up
        _damage(path, chunk.chunk_start_offset + 1, (10**15).to_bytes(8, "little"))
    kept = [e for e in range(EPISODES) if e != bad]
    unfinished = "unfinished" in where
    if unfinished:  # what a killed writer leaves: the data section without the summary
        last = chunks[-1]
        os.truncate(path, last.chunk_start_offset + last.chunk_length + last.message_index_length)

    reader = ArchiveReader(path)
    assert [m["episode"] for m in reader.episodes()] == kept and reader.finished != unfinished
    assert any(f"at byte {chunk.chunk_start_offset}" in w for w in reader.warnings), reader.warnings
    assert any(f"episode {bad} missing" in w for w in reader.warnings), reader.warnings
    for index, e in enumerate(kept):
        _assert_same_episode(reader.episode(index), recorded, e)

    assert main(["archive", "info", path]) == 0
    captured = capsys.readouterr()
    assert f"{len(kept)} complete episode(s)" in captured.out
    assert f"warning: {path}: skipped" in captured.err and "Traceback" not in captured.err
    gif = tmp_path / "last.gif"
    # replay takes the numbers info lists: after the lost episode too, and the lost one is an error.
    assert main(["archive", "replay", path, "--episode", str(kept[-1]), "--out", str(gif)]) == 0
    out = capsys.readouterr().out
    assert f"(episode {kept[-1]}: " in out
    assert reader.position(kept[-1]) == len(kept) - 1
    assert main(["archive", "replay", path, "--episode", str(bad), "--out", str(tmp_path / "lost.gif")]) == 2
    err = capsys.readouterr().err
    listed = {0: "1..2", 1: "0, 2"}[bad]
    assert f"has no episode {bad}; its complete episodes are {listed}" in err, err
    assert [line.startswith("warning:") for line in err.strip().splitlines()].count(False) == 1, err
    assert "Traceback" not in err
    assert not (tmp_path / "lost.gif").exists()
    fixed = tmp_path / "fixed.mcap"
    assert main(["archive", "recover", path, "--out", str(fixed)]) == 0
    captured = capsys.readouterr()
    assert f"{len(kept)} complete episode(s)" in captured.out and "skipped" in captured.err
    again = ArchiveReader(fixed)
    assert [m["episode"] for m in again.episodes()] == kept
    _assert_same_episode(again.episode(len(kept) - 1), recorded, kept[-1])


@pytest.mark.parametrize("field", ["start", "end"])
def test_damaged_chunk_header_times_are_detected(tmp_path, archive, recorded, field, capsys):
    """The header's message time range is outside the chunk CRC: 4 flipped bytes there must not pass
    as a clean file (replay would skip the chunk by its times and lose the episode)."""
    path = str(tmp_path / "times.mcap")
    shutil.copyfile(archive, path)
    chunk = _chunks(path)[1]
    at = chunk.chunk_start_offset + 1 + 8 + (0 if field == "start" else 8) + 2  # opcode, length, then the field
    _damage(path, at, bytes(b ^ 0xFF for b in open(path, "rb").read()[at : at + 4]))

    reader = ArchiveReader(path)
    assert len(reader) == EPISODES  # the messages passed their CRC: nothing is lost ...
    assert any(
        f"chunk at byte {chunk.chunk_start_offset}: its header gives message log times" in w for w in reader.warnings
    ), reader.warnings  # ... but the damage is reported
    _assert_same_episode(reader.episode(1), recorded, 1)  # not skipped by its (wrong) times
    assert main(["archive", "info", path]) == 0
    captured = capsys.readouterr()
    assert f"{EPISODES} complete episode(s)" in captured.out and "the header is damaged" in captured.err
    gif = tmp_path / "one.gif"
    assert main(["archive", "replay", path, "--episode", "1", "--out", str(gif)]) == 0 and gif.exists()
    capsys.readouterr()
    fixed = tmp_path / "fixed.mcap"
    assert main(["archive", "recover", path, "--out", str(fixed)]) == 0
    captured = capsys.readouterr()
    assert "the header is damaged" in captured.err and f"recovered {EPISODES} complete episode(s)" in captured.out
    again = ArchiveReader(fixed)  # the copy has correct headers
    assert again.warnings == [] and len(again) == EPISODES
    _assert_same_episode(again.episode(1), recorded, 1)


def _rewrite(src, dst, commit=None, step_metadata=None):
    """Copy an archive message for message, editing its commit records or step channel metadata."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out)
        writer.start(profile="ocv2-archive")
        ids, schemas = {}, {}
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.id not in ids:
                schema_id = 0
                if schema is not None:
                    schemas.setdefault(schema.id, writer.register_schema(schema.name, schema.encoding, schema.data))
                    schema_id = schemas[schema.id]
                metadata = dict(channel.metadata)
                if channel.topic == "step" and step_metadata:
                    metadata.update(step_metadata)
                ids[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schema_id, metadata)
            data = message.data
            if channel.topic == "episode" and commit is not None:
                data = commit(json.loads(data))
            writer.add_message(ids[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()


def _field_table_with(path, field_name, **changes):
    with open(path, "rb") as f:
        channel = next(c for c in make_reader(f).get_summary().channels.values() if c.topic == "step")
    table = json.loads(channel.metadata["fields"])
    next(field for field in table if field["name"] == field_name).update(changes)
    return json.dumps(table)


def test_crafted_records_are_one_line_errors(tmp_path, archive, capsys):
    """Commit records or step metadata that do not follow the format: a one-line error naming file,
    episode and key -- never a traceback, never a huge allocation."""

    def edited(**changes):
        return lambda meta: json.dumps({**meta, **changes}).encode()

    def without(key):
        return lambda meta: json.dumps({k: v for k, v in meta.items() if k != key}).encode()

    opening = [  # refused when the file is opened (info)
        (dict(commit=lambda meta: b"{not json"), "is not JSON"),
        (dict(commit=lambda meta: b"[1, 2]"), "not an object"),
        (dict(commit=lambda meta: b"[" * 100_000 + b"]" * 100_000), "nested deeper than 32 levels"),
        (dict(commit=without("steps")), "episode 0: the episode record has no 'steps'"),
        (dict(commit=edited(steps=10**12)), "key 'steps' is 1000000000000"),
        (dict(commit=edited(steps=-3)), "key 'steps' is -3"),
        (dict(commit=edited(num_agents="two")), "key 'num_agents' is 'two'"),
        # a later format may give the same keys other meanings: refused, not read as this one
        (dict(commit=edited(format_version=99)), "episode 0: format_version 99; this ocv2 reads version 1"),
    ]
    decoding = [  # refused when an episode is decoded (replay)
        (dict(step_metadata={"fields": "[not json"}), "key 'fields' is not JSON"),
        (dict(step_metadata={"fields": _field_table_with(archive, "state.grid", dtype="|O")}), "dtype '|O'"),
        (
            dict(step_metadata={"fields": _field_table_with(archive, "state.grid", shape=[4, 5, 2])}),
            "step message 0 has 311 bytes",
        ),
        (
            dict(step_metadata={"fields": _field_table_with(archive, "action", dtype="<f4")}),
            "action has dtype '<f4', not '<i4'",
        ),
        (
            dict(step_metadata={"fields": _field_table_with(archive, "state.grid", shape=[5, 4, 3])}),
            "states do not fit",
        ),
        (dict(step_metadata={"layout": "{}"}), "key 'layout'"),
        (dict(step_metadata={"byte_order": "big"}), "byte_order 'big'"),
        (  # another version's field table: the file (one of several SA archives, say) is named
            dict(step_metadata={"fields": _field_table_with(archive, "state.grid", name="state.board")}),
            "step fields",
        ),
        (dict(step_metadata={"layout": "[" * 5000 + "]" * 5000}), "nested deeper than 32 levels"),
    ]
    # A crafted record after good episodes: recover stops with the error and leaves no half-copied file.
    path, out = str(tmp_path / "late.mcap"), tmp_path / "late_fixed.mcap"
    _rewrite(archive, path, commit=lambda meta: b"{" if meta["episode"] == 2 else json.dumps(meta).encode())
    assert main(["archive", "recover", path, "--out", str(out)]) == 2
    assert "episode record at log time" in capsys.readouterr().err
    assert not out.exists() and not os.path.exists(str(out) + ".recovering")
    for n, (edit, message) in enumerate(opening + decoding):
        path = str(tmp_path / f"crafted_{n}.mcap")
        _rewrite(archive, path, **edit)
        argv = (
            ["archive", "info", path]
            if n < len(opening)
            else ["archive", "replay", path, "--out", str(tmp_path / f"crafted_{n}.gif")]
        )
        assert main(argv) == 2, (argv, edit)
        err = capsys.readouterr().err
        assert message in err and path in err and "Traceback" not in err, (message, err)
        assert len(err.strip().splitlines()) == 1, err


def _into_closed_pipe(argv: list[str]) -> subprocess.CompletedProcess:
    """Run ``ocv2 ARGV`` with stdout a pipe whose reader has already gone (``| head -0``, or a ``head -1``
    that read its line before the rest arrived): every write fails with EPIPE, deterministically."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run(
            [sys.executable, "-m", "cluster.cli", *argv],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
            timeout=120,
            env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": REPO},
        )
    finally:
        os.close(write)


@pytest.mark.parametrize(
    "argv", [["archive", "info", "ARCHIVE", "--limit", "-1"], ["archive", "info", "ARCHIVE", "--json"], ["layouts"]]
)
def test_piping_into_a_reader_that_closes_early_exits_quietly(archive, argv):
    child = _into_closed_pipe([archive if a == "ARCHIVE" else a for a in argv])
    assert child.stderr == "" and child.returncode == 1, child.stderr
