"""The Button Game (paper section 4): rules, independent Q-learning, the cross-play matrix, the CLI."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from cluster.cli import main
from population import button_game as bg

DEFAULT_GAME = bg.ButtonGameConfig()
DEFAULT_IQL = bg.IQLConfig()
NUM_SEEDS = 10


@pytest.fixture(scope="module")
def population():
    return bg.train_population(0, NUM_SEEDS, DEFAULT_GAME, DEFAULT_IQL)


@pytest.fixture(scope="module")
def xp(population):
    return bg.evaluate_population(population, DEFAULT_GAME)


# --- the environment ---------------------------------------------------------------------------------


@pytest.mark.parametrize("num_buttons", [2, 5])
def test_reward_rule_bulb_is_2a_plus_pet(num_buttons):
    game = bg.ButtonGameConfig(num_buttons=num_buttons, reward=10.0)
    pet, button, guess = np.meshgrid(np.arange(2), np.arange(num_buttons), np.arange(2), indexing="ij")
    played = jax.jit(jax.vmap(bg.play, in_axes=(0, 0, 0, None)), static_argnums=3)(
        pet.ravel(), button.ravel(), guess.ravel(), game
    )
    np.testing.assert_array_equal(played.bulb, 2 * button.ravel() + pet.ravel())
    np.testing.assert_array_equal(played.bulb % 2, pet.ravel())  # the parity is the pet
    np.testing.assert_array_equal(played.reward, np.where(guess.ravel() == pet.ravel(), 10.0, -10.0))
    obs = bg.bob_observation(played.bulb, game)
    assert obs.shape == (pet.size, 2 * num_buttons)
    np.testing.assert_array_equal(np.argmax(obs, axis=-1), played.bulb)
    np.testing.assert_array_equal(obs.sum(-1), 1.0)


def test_pet_is_uniform():
    pets = jax.vmap(bg.sample_pet)(jax.random.split(jax.random.PRNGKey(0), 4000))
    assert set(np.unique(pets)) == {0, 1}
    assert abs(float(pets.mean()) - 0.5) < 0.03


@pytest.mark.parametrize(
    "kwargs, bad",
    [
        (dict(num_buttons=1), "1"),
        (dict(num_buttons=2.5), "2.5"),
        (dict(num_buttons=True), "True"),
        (dict(reward=0.0), "0.0"),
    ],
)
def test_game_config_names_bad_value(kwargs, bad):
    with pytest.raises(ValueError, match=rf"{next(iter(kwargs))}.*{bad}"):
        bg.ButtonGameConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs, bad",
    [
        (dict(episodes=0), "0"),
        (dict(epsilon=1.5), "1.5"),
        (dict(learning_rate=0.0), "0.0"),
        (dict(init_scale=-1.0), "-1.0"),
    ],
)
def test_iql_config_names_bad_value(kwargs, bad):
    with pytest.raises(ValueError, match=rf"{next(iter(kwargs))}.*{bad}"):
        bg.IQLConfig(**kwargs)


def test_train_population_rejects_zero_seeds():
    with pytest.raises(ValueError, match="num_seeds.*0"):
        bg.train_population(0, 0, DEFAULT_GAME, DEFAULT_IQL)


# --- the learning rule -------------------------------------------------------------------------------


def test_q_update_is_one_step_rule():
    q = jnp.array([[1.0, 2.0], [3.0, 4.0]])
    new = bg.q_update(q, 1, 0, 10.0, 0.25)
    np.testing.assert_allclose(new, [[1.0, 2.0], [3.0 + 0.25 * (10.0 - 3.0), 4.0]])


def test_epsilon_greedy_extremes():
    keys = jax.random.split(jax.random.PRNGKey(1), 2000)
    q_row = jnp.array([0.0, 5.0, 1.0, 2.0])
    greedy = jax.vmap(bg.epsilon_greedy, in_axes=(0, None, None))(keys, q_row, 0.0)
    assert set(np.unique(greedy)) == {1}
    random = jax.vmap(bg.epsilon_greedy, in_axes=(0, None, None))(keys, q_row, 1.0)
    counts = np.bincount(np.asarray(random), minlength=4)
    assert counts.min() > 400  # ~500 each


def test_training_history_follows_the_rules_and_learns():
    result = bg.train_pair(jax.random.PRNGKey(3), DEFAULT_GAME, DEFAULT_IQL)
    h = result.history
    assert h.pet.shape == (DEFAULT_IQL.episodes,)
    np.testing.assert_array_equal(h.bulb, 2 * h.button + h.pet)
    np.testing.assert_array_equal(h.reward, np.where(h.guess == h.pet, 10.0, -10.0))
    assert float(h.reward[-100:].mean()) > 9.0  # only exploration costs reward
    assert float(h.reward[:5].mean()) < float(h.reward[-100:].mean())


# --- exact evaluation --------------------------------------------------------------------------------


def test_expected_reward_by_hand():
    game = bg.ButtonGameConfig(num_buttons=2)
    alice = jnp.array([[1.0, 0.0], [0.0, 1.0]])  # cat -> button 0 (bulb 0), dog -> button 1 (bulb 3)
    assert float(bg.expected_reward(alice, jnp.array([0, 1, 0, 1]), game)) == 10.0
    assert float(bg.expected_reward(alice, jnp.array([0, 1, 0, 0]), game)) == 0.0  # wrong on bulb 3
    assert float(bg.expected_reward(alice, jnp.array([1, 0, 1, 0]), game)) == -10.0
    uniform = bg.uniform_alice(game)
    # cat lights bulbs 0 and 2 (guesses 0: right, 1: wrong) -> 0; dog lights 1 and 3 (both right) -> +10
    assert float(bg.expected_reward(uniform, jnp.array([0, 1, 1, 1]), game)) == pytest.approx(5.0)


def test_expected_reward_matches_sampled_games():
    game = bg.ButtonGameConfig(num_buttons=3)
    rng = np.random.default_rng(0)
    probs = rng.dirichlet(np.ones(3), size=2)  # a stochastic Alice
    guesses = rng.integers(0, 2, size=6)
    pets = rng.integers(0, 2, size=200_000)
    buttons = np.where(pets == 0, rng.choice(3, size=pets.size, p=probs[0]), rng.choice(3, size=pets.size, p=probs[1]))
    sampled = np.where(guesses[2 * buttons + pets] == pets, 10.0, -10.0).mean()
    exact = float(bg.expected_reward(jnp.asarray(probs, jnp.float32), jnp.asarray(guesses), game))
    assert exact == pytest.approx(sampled, abs=0.1)  # sampling s.e. ~0.02


def test_summarize_by_hand():
    matrix = np.array([[10.0, 0.0, 10.0], [-10.0, 10.0, 10.0], [5.0, 2.0, 10.0]])
    assert bg.summarize(matrix, 2) == (10.0, -5.0, 10.0, 10.0)


# --- the paper's result ------------------------------------------------------------------------------


def test_every_self_play_pair_scores_10(xp):
    assert xp.matrix.shape == (NUM_SEEDS + 1, NUM_SEEDS + 1)
    np.testing.assert_array_equal(np.diag(xp.matrix)[:NUM_SEEDS], 10.0)
    assert xp.sp_mean == 10.0


def test_best_response_scores_10_with_every_alice(xp, population):
    np.testing.assert_array_equal(xp.matrix[:, -1], 10.0)  # every SP Alice and the random one
    assert xp.br_mean == 10.0 and xp.br_random_alice == 10.0
    # why: it reads the pet off the bulb's parity, on every bulb
    np.testing.assert_array_equal(bg.greedy_bob(population.br_bob), np.arange(DEFAULT_GAME.num_bulbs) % 2)


def test_cross_play_fails_between_self_play_pairs(xp, population):
    assert xp.xp_mean < 5.0 < xp.sp_mean
    conventions = {tuple(np.asarray(jnp.argmax(a, axis=-1))) for a in population.sp.alice}
    assert len(conventions) > 1  # pairs settle on different buttons
    # the SP Bobs have not learned every bulb: a random Alice does worse with most of them
    assert np.mean(xp.matrix[-1, :NUM_SEEDS] < 10.0) >= 0.5


def test_cross_play_failure_is_state_coverage():
    """Explore enough that every SP Bob sees every bulb and cross-play reaches self-play."""
    iql = dataclasses.replace(DEFAULT_IQL, epsilon=0.3, episodes=2000)
    result = bg.run_button_game(seed=0, num_seeds=NUM_SEEDS, game=DEFAULT_GAME, iql=iql)
    assert result.sp_mean == 10.0 and result.xp_mean == 10.0 and result.br_mean == 10.0


def test_pair_does_not_depend_on_number_of_seeds(population):
    few = bg.train_population(0, 3, DEFAULT_GAME, DEFAULT_IQL)
    np.testing.assert_allclose(few.sp.alice, population.sp.alice[:3], rtol=1e-6)
    np.testing.assert_allclose(few.sp.bob, population.sp.bob[:3], rtol=1e-6)
    np.testing.assert_allclose(few.br_bob, population.br_bob, rtol=1e-6)
    other = bg.train_population(1, 3, DEFAULT_GAME, DEFAULT_IQL)
    assert not np.allclose(other.sp.alice, few.sp.alice)


# --- output and CLI ----------------------------------------------------------------------------------


def test_csv_round_trip(tmp_path, xp):
    path = tmp_path / "m.csv"
    bg.write_csv(path, xp.matrix, xp.labels)
    matrix, labels = bg.read_csv(path)
    assert labels == xp.labels and labels[0] == "SP pair 1" and labels[-1] == "BR"
    np.testing.assert_allclose(matrix, xp.matrix)


def test_cli_writes_csv_and_png(tmp_path, capsys):
    out = tmp_path / "bg"
    assert main(["button-game", "--seeds", "4", "--out", str(out), "--seed", "0", "--buttons", "8"]) == 0
    printed = capsys.readouterr().out
    assert "SP" in printed and "XP" in printed and "BR" in printed
    matrix, labels = bg.read_csv(out / "button_game_xp.csv")
    assert labels == ("SP pair 1", "SP pair 2", "SP pair 3", "SP pair 4", "BR")
    np.testing.assert_array_equal(np.diag(matrix), 10.0)
    np.testing.assert_array_equal(matrix[:, -1], 10.0)
    assert f"{np.mean(matrix[:4, :4][~np.eye(4, dtype=bool)]):+.2f}" in printed
    with Image.open(out / "button_game_xp.png") as image:
        assert image.format == "PNG" and min(image.size) > 200


def test_cli_keeps_earlier_results_unless_forced_and_titles_the_settings_used(tmp_path, capsys, monkeypatch):
    from cluster.cli import button_game as cmd

    out = tmp_path / "bg"
    argv = ["button-game", "--seeds", "2", "--episodes", "50", "--out", str(out)]
    assert main(argv) == 0
    first = (out / "button_game_xp.csv").read_bytes()
    assert main([*argv, "--seed", "7"]) == 2
    assert "holds button_game_xp.csv and button_game_xp.png of an earlier run" in capsys.readouterr().err
    assert (out / "button_game_xp.csv").read_bytes() == first
    titles = []
    monkeypatch.setattr(cmd, "plot_heatmap", lambda path, matrix, labels, title: titles.append(title))
    assert main([*argv, "--seed", "7", "--epsilon", "0.2", "--force"]) == 0
    assert "eps=0.2" in titles[0] and "seed 7" in titles[0]  # the title said eps=0.01 whatever was asked


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["--buttons", "1"], "--buttons"),
        (["--seeds", "0"], "--seeds"),
        (["--epsilon", "2"], "--epsilon"),
    ],
)
def test_cli_bad_input(tmp_path, capsys, argv, flag):
    out = tmp_path / "never"
    assert main(["button-game", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err
    assert flag in err and argv[1] in err and "Traceback" not in err
    assert not out.exists()


def test_cli_out_is_a_file(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["button-game", "--out", str(blocker)]) == 2
    assert "not a folder" in capsys.readouterr().err
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("{}")
    assert main(["button-game", "--out", str(run)]) == 2  # not among a training run's files
    assert "is a run directory" in capsys.readouterr().err and sorted(p.name for p in run.iterdir()) == ["config.yaml"]


def test_cli_defaults_match_configs():
    from cluster.cli import button_game as cmd

    assert cmd.DEFAULT_BUTTONS == DEFAULT_GAME.num_buttons
    assert (cmd.DEFAULT_EPISODES, cmd.DEFAULT_EPSILON, cmd.DEFAULT_LR) == (
        DEFAULT_IQL.episodes,
        DEFAULT_IQL.epsilon,
        DEFAULT_IQL.learning_rate,
    )
