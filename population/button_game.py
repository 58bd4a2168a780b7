"""The Button Game (OvercookedV2 paper, section 4): a one-step signalling game in pure JAX.

Alice sees a pet (``pet`` 0 = cat, 1 = dog, uniform) and presses one of ``N`` buttons. Pressing button
``a`` lights bulb ``2a + pet`` of ``2N`` bulbs. Bob sees the lit bulb (one-hot) and guesses the pet;
both get ``+10`` if he is right and ``-10`` if not.

The game needs no convention at all: the bulb's parity *is* the pet (``pet = bulb % 2``). Self-play
pairs trained with independent Q-learning still fail in cross-play, because each Bob only learns the
bulbs his own Alice lights: a new Alice lights bulbs he never saw, and there his greedy guess is a
coin flip set by his random initial Q-values. A best-response Bob trained against a uniformly random
Alice has seen every bulb and scores +10 with every Alice. The failure is one of *state coverage*,
not of coordination.

Everything is a pure function of explicit PRNG keys; configurations are frozen (hashable) dataclasses
passed as static arguments, so training jits and vmaps over seeds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

CAT, DOG = 0, 1
NUM_PETS = 2
#: ``fold_in`` data for the best-response Bob's key; far above any SP seed index, so the BR agent
#: is the same whatever number of self-play seeds is trained.
BR_STREAM = 0x7FFFFFFF


# ---------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class ButtonGameConfig:
    """The game: ``num_buttons`` buttons (so ``2 * num_buttons`` bulbs) and the +/- reward size."""

    num_buttons: int = 8
    reward: float = 10.0

    def __post_init__(self):
        if not _is_int(self.num_buttons) or self.num_buttons < 2:
            raise ValueError(f"num_buttons must be an integer >= 2, got {self.num_buttons!r}")
        if not isinstance(self.reward, (int, float)) or not math.isfinite(self.reward) or self.reward <= 0:
            raise ValueError(f"reward must be a finite number > 0, got {self.reward!r}")

    @property
    def num_bulbs(self) -> int:
        return 2 * self.num_buttons


@dataclasses.dataclass(frozen=True)
class IQLConfig:
    """Tabular independent Q-learning: epsilon-greedy for both players, ``Q += lr * (r - Q)``.

    ``init_scale``: Q-tables start uniform in ``[0, init_scale)``, far below the reward, so the first
    greedy choices are random tie-breaks; that is what lets different seeds settle on different
    buttons (with all-zero tables every Alice would press button 0).

    The defaults explore little (epsilon 0.01 over 200 games; a pair converges within a few games),
    so a self-play Bob sees few bulbs beyond those his own Alice lit. With ``epsilon * episodes`` well
    above ``2N`` every Bob learns every bulb and cross-play climbs to self-play: the failure is state
    coverage (docs/button_game.md).
    """

    episodes: int = 200
    epsilon: float = 0.01
    learning_rate: float = 0.1
    init_scale: float = 0.1

    def __post_init__(self):
        if not _is_int(self.episodes) or self.episodes < 1:
            raise ValueError(f"episodes must be an integer >= 1, got {self.episodes!r}")
        if not isinstance(self.epsilon, (int, float)) or not 0.0 <= self.epsilon <= 1.0:
            raise ValueError(f"epsilon must be in [0, 1], got {self.epsilon!r}")
        if not isinstance(self.learning_rate, (int, float)) or not 0.0 < self.learning_rate <= 1.0:
            raise ValueError(f"learning_rate must be in (0, 1], got {self.learning_rate!r}")
        if not isinstance(self.init_scale, (int, float)) or not math.isfinite(self.init_scale) or self.init_scale < 0:
            raise ValueError(f"init_scale must be a finite number >= 0, got {self.init_scale!r}")


# ---------------------------------------------------------------------------------------------------
# containers
# ---------------------------------------------------------------------------------------------------


class Transition(NamedTuple):
    """One played game (the whole episode: the game has a single step)."""

    pet: jax.Array  # int, 0 cat / 1 dog
    button: jax.Array  # int in [0, N)
    bulb: jax.Array  # int in [0, 2N): 2 * button + pet
    guess: jax.Array  # int, Bob's guess of the pet
    reward: jax.Array  # float, +reward or -reward, shared by both players


class QTables(NamedTuple):
    """Both players' tables: ``alice[pet, button]`` and ``bob[bulb, guess]``."""

    alice: jax.Array  # (2, N)
    bob: jax.Array  # (2N, 2)


class TrainResult(NamedTuple):
    """Final Q-tables and every training game (leading axis: episode; ``None`` unless kept)."""

    q: QTables
    history: Transition | None


class Population(NamedTuple):
    """``num_seeds`` self-play pairs (Q-tables stacked on a leading seed axis) and the BR Bob."""

    sp: QTables  # alice (S, 2, N), bob (S, 2N, 2)
    br_bob: jax.Array  # (2N, 2), trained against a uniformly random Alice


class CrossPlay(NamedTuple):
    """The (S+1) x (S+1) matrix: rows are Alices, columns Bobs; the last row/column is "BR".

    ``matrix[i, j]`` is the exact expected reward of Alice ``i`` with Bob ``j`` (greedy policies,
    averaged over both pets). The BR column is the best-response Bob; the BR row is the uniformly
    random Alice he was trained with (the BR agent is a Bob only), so ``matrix[BR, j]`` measures how
    much of the bulb space Bob ``j`` has learned.
    """

    matrix: np.ndarray
    labels: tuple[str, ...]
    sp_mean: float  # diagonal over SP pairs
    xp_mean: float  # off-diagonal over SP pairs
    br_mean: float  # BR Bob with every SP Alice
    br_random_alice: float  # BR Bob with the random Alice he trained with


# ---------------------------------------------------------------------------------------------------
# the environment
# ---------------------------------------------------------------------------------------------------


def sample_pet(key: jax.Array) -> jax.Array:
    """The hidden state: cat (0) or dog (1), uniform."""
    return jax.random.randint(key, (), 0, NUM_PETS)


def bulb_index(button, pet) -> jax.Array:
    """Button ``a`` with pet ``p`` lights bulb ``2a + p``; its parity reveals the pet."""
    return 2 * jnp.asarray(button) + jnp.asarray(pet)


def bob_observation(bulb, game: ButtonGameConfig) -> jax.Array:
    """What Bob sees: the lit bulb, one-hot over the ``2N`` bulbs."""
    return jax.nn.one_hot(bulb, game.num_bulbs, dtype=jnp.float32)


def reward(pet, guess, game: ButtonGameConfig) -> jax.Array:
    """Shared reward: ``+reward`` if Bob guessed the pet, ``-reward`` otherwise."""
    return jnp.where(jnp.asarray(guess) == jnp.asarray(pet), game.reward, -game.reward).astype(jnp.float32)


def play(pet, button, guess, game: ButtonGameConfig) -> Transition:
    """The whole one-step game for given choices (Bob picks ``guess`` seeing only the lit bulb)."""
    pet, button, guess = jnp.asarray(pet), jnp.asarray(button), jnp.asarray(guess)
    return Transition(
        pet=pet, button=button, bulb=bulb_index(button, pet), guess=guess, reward=reward(pet, guess, game)
    )


# ---------------------------------------------------------------------------------------------------
# independent Q-learning
# ---------------------------------------------------------------------------------------------------


def epsilon_greedy(key: jax.Array, q_row: jax.Array, epsilon: float) -> jax.Array:
    """With probability ``epsilon`` a uniformly random action, else ``argmax q_row``."""
    explore_key, action_key = jax.random.split(key)
    random_action = jax.random.randint(action_key, (), 0, q_row.shape[-1])
    explore = jax.random.uniform(explore_key) < epsilon
    return jnp.where(explore, random_action, jnp.argmax(q_row)).astype(jnp.int32)


def q_update(q: jax.Array, state, action, target, learning_rate: float) -> jax.Array:
    """One-step game, no bootstrap: ``Q[s, a] += lr * (r - Q[s, a])``."""
    return q.at[state, action].add(learning_rate * (target - q[state, action]))


def init_q_tables(key: jax.Array, game: ButtonGameConfig, iql: IQLConfig) -> QTables:
    """Small random tables (see ``IQLConfig.init_scale``): random tie-breaks, diverse conventions."""
    alice_key, bob_key = jax.random.split(key)
    return QTables(
        alice=iql.init_scale * jax.random.uniform(alice_key, (NUM_PETS, game.num_buttons)),
        bob=iql.init_scale * jax.random.uniform(bob_key, (game.num_bulbs, NUM_PETS)),
    )


def train_episode(
    q: QTables, key: jax.Array, game: ButtonGameConfig, iql: IQLConfig, random_alice: bool = False
) -> tuple[QTables, Transition]:
    """Play one game and update both learners (a ``lax.scan`` body).

    ``random_alice``: Alice presses a uniformly random button and does not learn (best-response
    training for Bob); otherwise both players are independent epsilon-greedy Q-learners.
    """
    pet_key, alice_key, bob_key = jax.random.split(key, 3)
    pet = sample_pet(pet_key)
    if random_alice:
        button = jax.random.randint(alice_key, (), 0, game.num_buttons)
    else:
        button = epsilon_greedy(alice_key, q.alice[pet], iql.epsilon)
    bulb = bulb_index(button, pet)
    guess = epsilon_greedy(bob_key, q.bob[bulb], iql.epsilon)
    game_played = play(pet, button, guess, game)
    alice = q.alice if random_alice else q_update(q.alice, pet, button, game_played.reward, iql.learning_rate)
    bob = q_update(q.bob, bulb, guess, game_played.reward, iql.learning_rate)
    return QTables(alice=alice, bob=bob), game_played


def _episode_no_history(
    q: QTables, key: jax.Array, game: ButtonGameConfig, iql: IQLConfig, random_alice: bool
) -> tuple[QTables, None]:
    """``train_episode`` that keeps nothing per game (long runs need no O(episodes) memory)."""
    return train_episode(q, key, game, iql, random_alice)[0], None


@functools.partial(jax.jit, static_argnames=("game", "iql", "random_alice", "keep_history"))
def train_pair(
    key: jax.Array, game: ButtonGameConfig, iql: IQLConfig, random_alice: bool = False, keep_history: bool = True
) -> TrainResult:
    """Train one Alice/Bob pair for ``iql.episodes`` games with ``lax.scan``."""
    init_key, games_key = jax.random.split(key)
    step = train_episode if keep_history else _episode_no_history
    body = functools.partial(step, game=game, iql=iql, random_alice=random_alice)
    q, history = jax.lax.scan(body, init_q_tables(init_key, game, iql), jax.random.split(games_key, iql.episodes))
    return TrainResult(q=q, history=history)


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """Seed ``i``'s key is ``fold_in(PRNGKey(seed), i)``: independent of how many seeds are trained."""
    root = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(num_seeds, dtype=jnp.uint32))


def train_best_response_bob(seed: int, game: ButtonGameConfig, iql: IQLConfig) -> jax.Array:
    """Bob trained against a uniformly random Alice (key ``fold_in(PRNGKey(seed), BR_STREAM)``)."""
    key = jax.random.fold_in(jax.random.PRNGKey(seed), BR_STREAM)
    return train_pair(key, game, iql, random_alice=True, keep_history=False).q.bob


def train_population(seed: int, num_seeds: int, game: ButtonGameConfig, iql: IQLConfig) -> Population:
    """``num_seeds`` independently seeded self-play pairs (vmapped) plus the best-response Bob."""
    if not _is_int(num_seeds) or num_seeds < 1:
        raise ValueError(f"num_seeds must be an integer >= 1, got {num_seeds!r}")
    train_sp = jax.vmap(functools.partial(train_pair, game=game, iql=iql, keep_history=False))
    sp = train_sp(seed_keys(seed, num_seeds)).q
    return Population(sp=sp, br_bob=train_best_response_bob(seed, game, iql))


# ---------------------------------------------------------------------------------------------------
# evaluation: exact expectations of greedy policies
# ---------------------------------------------------------------------------------------------------


def greedy_alice(q_alice: jax.Array) -> jax.Array:
    """Greedy Alice as a policy matrix ``probs[pet, button]`` (one-hot rows)."""
    return jax.nn.one_hot(jnp.argmax(q_alice, axis=-1), q_alice.shape[-1], dtype=jnp.float32)


def uniform_alice(game: ButtonGameConfig) -> jax.Array:
    """The random Alice the best response is trained with: every button with probability 1/N."""
    return jnp.full((NUM_PETS, game.num_buttons), 1.0 / game.num_buttons, dtype=jnp.float32)


def greedy_bob(q_bob: jax.Array) -> jax.Array:
    """Greedy Bob: his guess for every bulb, shape ``(2N,)``."""
    return jnp.argmax(q_bob, axis=-1)


def expected_reward(alice_probs: jax.Array, bob_guesses: jax.Array, game: ButtonGameConfig) -> jax.Array:
    """Exact expected reward: ``sum_p 1/2 sum_a probs[p, a] * r(p, guess[2a + p])`` (no sampling)."""
    pets = jnp.arange(NUM_PETS)[:, None]
    buttons = jnp.arange(game.num_buttons)[None, :]
    rewards = reward(pets, bob_guesses[bulb_index(buttons, pets)], game)  # (2, N)
    return jnp.sum(alice_probs * rewards) / NUM_PETS


def cross_play_matrix(alice_probs: jax.Array, bob_guesses: jax.Array, game: ButtonGameConfig) -> jax.Array:
    """``M[i, j]`` = expected reward of Alice ``i`` (``(A, 2, N)`` policies) with Bob ``j`` (``(B, 2N)``)."""
    per_bob = jax.vmap(expected_reward, in_axes=(None, 0, None))
    return jax.vmap(per_bob, in_axes=(0, None, None))(alice_probs, bob_guesses, game)


def summarize(matrix, num_seeds: int) -> tuple[float, float, float, float]:
    """(SP, XP, BR, BR-with-random-Alice) means of an (S+1) x (S+1) cross-play matrix."""
    matrix = np.asarray(matrix, dtype=np.float64)
    sp_block = matrix[:num_seeds, :num_seeds]
    sp = float(np.mean(np.diag(sp_block)))
    off = ~np.eye(num_seeds, dtype=bool)
    xp = float(np.mean(sp_block[off])) if num_seeds > 1 else float("nan")
    br = float(np.mean(matrix[:num_seeds, num_seeds]))
    return sp, xp, br, float(matrix[num_seeds, num_seeds])


def labels_for(num_seeds: int) -> tuple[str, ...]:
    """Row/column labels: ``SP pair 1`` ... ``SP pair S`` and ``BR``."""
    return tuple(f"SP pair {i + 1}" for i in range(num_seeds)) + ("BR",)


def evaluate_population(population: Population, game: ButtonGameConfig) -> CrossPlay:
    """Every SP Alice plus the random Alice against every SP Bob plus the BR Bob."""
    num_seeds = population.sp.alice.shape[0]
    alices = jnp.concatenate([jax.vmap(greedy_alice)(population.sp.alice), uniform_alice(game)[None]])
    bobs = jnp.concatenate([jax.vmap(greedy_bob)(population.sp.bob), greedy_bob(population.br_bob)[None]])
    # Rounded: float32 sums of 1/N probabilities leave ~1e-6 noise on the random-Alice row.
    matrix = np.round(np.asarray(cross_play_matrix(alices, bobs, game), dtype=np.float64), 4)
    sp, xp, br, br_random = summarize(matrix, num_seeds)
    return CrossPlay(
        matrix=matrix, labels=labels_for(num_seeds), sp_mean=sp, xp_mean=xp, br_mean=br, br_random_alice=br_random
    )


def run_button_game(
    seed: int = 0, num_seeds: int = 10, game: ButtonGameConfig = ButtonGameConfig(), iql: IQLConfig = IQLConfig()
) -> CrossPlay:
    """Train the population and return its cross-play matrix (what ``ocv2 button-game`` does)."""
    return evaluate_population(train_population(seed, num_seeds, game, iql), game)


# ---------------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------------


def write_csv(path, matrix, labels: Sequence[str]) -> None:
    """The matrix with a header row of Bob labels and a first column of Alice labels."""
    import csv

    matrix = np.asarray(matrix)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["Alice \\ Bob", *labels])
        for label, row in zip(labels, matrix):
            writer.writerow([label, *(f"{value:g}" for value in row)])


def read_csv(path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Inverse of ``write_csv``: (matrix, labels)."""
    import csv

    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    labels = tuple(rows[0][1:])
    return np.array([[float(v) for v in row[1:]] for row in rows[1:]]), labels


def plot_heatmap(path, matrix, labels: Sequence[str], title: str = "Button Game cross-play") -> None:
    """An annotated heatmap like the paper's Figure 3 (Agg canvas; no pyplot global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    matrix = np.asarray(matrix)
    size = len(labels)
    figure = Figure(figsize=(1.0 + 0.62 * size, 0.8 + 0.55 * size), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    limit = max(float(np.max(np.abs(matrix))), 1e-9)
    image = axes.imshow(matrix, cmap="RdYlGn", vmin=-limit, vmax=limit)
    axes.set_xticks(range(size), labels, rotation=45, ha="right")
    axes.set_yticks(range(size), labels)
    axes.set_xlabel("Bob (BR: best response to a uniformly random Alice)")
    axes.set_ylabel("Alice (BR: the uniformly random Alice)")
    axes.set_title(title)
    for i in range(size):
        for j in range(size):
            axes.text(j, i, f"{matrix[i, j]:.3g}", ha="center", va="center", fontsize=8, color="black")
    axes.axhline(size - 1.5, color="black", linewidth=1.5)  # set the BR row and column apart
    axes.axvline(size - 1.5, color="black", linewidth=1.5)
    figure.colorbar(image, ax=axes, label="expected reward")
    figure.tight_layout()
    figure.savefig(path)
