"""``ocv2 render --seats``: one episode of two trained policies to a GIF, from the published policy files
(docs/results/table1_coord_ring_sp10/policies/, update 30, and Forced Coord.'s for a pair that plays two
environments); ``population.evaluation.episode_states`` is the episode ``play_seats`` plays for the same key."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

from cluster.cli import main
from cluster.cli import render as render_cli
from cluster.runtime.rundir import RunDir
from population import checkpoints as ckpt
from population import ppo
from population.config import load_config
from population.evaluation import episode_states, play_seats
from population.networks import init_params
from population.policy import export, load

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
RING = RESULTS / "table1_coord_ring_sp10" / "policies"
SEAT0, SEAT1 = (str(RING / f"sp_seed{i}_update30.ocv2policy") for i in (0, 1))
FORCED = str(RESULTS / "table1_forced_coord_sp10" / "policies" / "sp_seed0_update30.ocv2policy")
SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")


@pytest.fixture(scope="module")
def rnn_run(tmp_path_factory):
    """A run directory with one untrained RNN checkpoint: a seat that carries a hidden state from step to step."""
    run = tmp_path_factory.mktemp("runs") / "rnn"
    overrides = ["model.kind=rnn", "model.gru_dim=8", "model.mixer_features=[8]", "model.conv_features=[8]"]
    config = load_config(SMOKE, [*overrides, "model.conv_kernels=[3]", "model.fc_dim=8", "env.max_steps=12"])
    RunDir(run).create(config)
    network = ppo.make_trainer(config).network
    params = jax.jit(lambda key: init_params(network, key, ppo.eval_env(config).obs_shape))(jax.random.PRNGKey(3))
    ckpt.save(ckpt.checkpoint_path(run, 0, 4), {"params": params}, config.fingerprint(), seed=0, update=4)
    return run


@pytest.mark.parametrize("kind", ["cnn", "rnn"])
def test_episode_states_is_the_episode_play_seats_plays_for_the_same_key(kind, request):
    first, second = (SEAT0, SEAT1) if kind == "cnn" else (request.getfixturevalue("rnn_run"),) * 2
    seats = [load(first).seat, load(second).seat]
    env = load(first).make_env()
    key = jax.random.PRNGKey(3)
    states, episode_return = jax.jit(lambda k: episode_states(seats, env, k))(key)
    played = play_seats(seats, env, key, episodes=1, keep_every=1)
    assert float(episode_return) == float(played.returns[0])
    assert states.step.shape == (env.max_steps + 1,)  # the reset state, then one per step
    assert int(states.step[-1]) == env.max_steps  # the last step's state, before the auto-reset
    for mine, theirs in zip(jax.tree.leaves(states), jax.tree.leaves(played.states)):
        np.testing.assert_array_equal(mine[:-1], theirs[0])


def test_render_seats_writes_the_pairs_episode_and_its_return(tmp_path, capsys):
    out = tmp_path / "pair.gif"
    argv = ["render", "--seats", SEAT0, SEAT1, "--steps", "4", "--tile-size", "8", "--seed", "3", "--out"]
    assert main([*argv, str(out)]) == 0
    printed = capsys.readouterr().out
    assert "5 frames (4 steps of coord_ring" in printed
    expected = episode_states([load(SEAT0).seat, load(SEAT1).seat], load(SEAT0).make_env(), jax.random.PRNGKey(3))[1]
    assert f"episode return {float(expected):g} over the whole 400-step episode (seed 3)" in printed
    with Image.open(out) as im:
        assert im.n_frames == 5 and im.size == (5 * 8, 5 * 8)  # Coordination Ring is 5 x 5
    # LAYOUT may be given when it is the seats' own
    assert main(["render", "coord_ring", *argv[1:], str(tmp_path / "again.gif")]) == 0


def test_render_seats_plays_a_recurrent_policy_from_its_run_directory(rnn_run, tmp_path, capsys):
    out = tmp_path / "rnn.gif"
    assert main(["render", "--seats", str(rnn_run), str(rnn_run), "--tile-size", "8", "--out", str(out)]) == 0
    assert "13 frames (12 steps of cramped_room" in capsys.readouterr().out  # the whole episode by default
    with Image.open(out) as im:
        assert im.n_frames == 13


def test_render_seats_plays_at_the_precision_the_policies_trained_with(rnn_run, tmp_path, monkeypatch, capsys):
    """As cross-play: on a GPU JAX's own default would be TF32 for policies trained at float32."""
    seen = []

    def recording_episode_states(*args, **kwargs):
        seen.append(jax.config.jax_default_matmul_precision)  # what the episode is traced under
        return episode_states(*args, **kwargs)

    monkeypatch.setattr(render_cli, "episode_states", recording_episode_states)
    policy = load(rnn_run)
    files = {}
    for precision in ("bf16", "fp16"):
        files[precision] = str(
            export(
                tmp_path / f"{precision}.bin",
                params=policy.params,
                model=policy.model,
                env=policy.env,
                meta={"precision": precision},
            )
        )
    run = str(rnn_run)  # its config says run.precision float32
    base = ["render", "--tile-size", "8", "--steps", "2", "--out"]
    for seats, extra, expected in [
        ((run, run), [], "float32"),
        ((files["bf16"], files["bf16"]), [], "bfloat16"),
        ((run, files["bf16"]), ["--precision", "tf32"], "tensorfloat32"),
    ]:
        assert main([*base, str(tmp_path / f"{expected}.gif"), "--seats", *seats, *extra]) == 0
        assert seen[-1] == expected
    assert jax.config.jax_default_matmul_precision is None  # only while the episode is traced
    capsys.readouterr()
    for seats, extra, message in [
        ((run, files["bf16"]), [], f"--seats: the sources trained at different run.precision ({run}"),
        ((run, files["bf16"]), [], "bf16); choose one with --precision"),
        ((files["fp16"], run), [], "--seats SEAT0: " + files["fp16"] + ": meta precision 'fp16' is not one of"),
        ((), ["cramped_room", "--precision", "tf32"], "--precision applies to --seats"),
    ]:
        seat_args = ["--seats", *seats] if seats else []
        assert main([*base, str(tmp_path / "refused.gif"), *seat_args, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    assert not (tmp_path / "refused.gif").exists() and len(seen) == 3


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seats", SEAT0, FORCED], "plays another environment than"),
        (["--seats", SEAT0, FORCED], "(differs in layout: 'forced_coord' vs 'coord_ring')"),
        (["forced_coord", "--seats", SEAT0, SEAT1], "the --seats policies play 'coord_ring'"),
        (["--seats", SEAT0, SEAT1, "--steps", "401"], "--steps 401: an episode of coord_ring has 400 steps"),
        (["--seats", SEAT0, "no_such.ocv2policy"], "--seats SEAT1: no_such.ocv2policy: no such file"),
        ([], "give a LAYOUT to render random actions on, or two policies with --seats"),
        (["coord_ring", "--greedy"], "--greedy applies to --seats"),
    ],
)
def test_render_seats_refuses_what_it_cannot_play(argv, message, tmp_path, capsys):
    out = tmp_path / "x.gif"
    assert main(["render", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()
