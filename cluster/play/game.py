"""The JAX side of ``ocv2 play``: partners, one jitted game step and the players' views.

Everything here is a pure function of explicit arguments (state, parameters, PRNG keys); the
session in ``cluster/play/session.py`` owns time, seats and recording. ``make_game`` jits the step
(partner policies + environment) and the view renderer once per session, so a tick costs two
compiled calls whatever the layout. They are traced at the matmul precision the partner trained with
(``run.precision``, from its run or an exported file's meta; float32 where nothing says), as cross-play
and ``ocv2 render --seats`` play it: on a GPU, JAX's own default would be TF32.

A partner follows the network calling convention of ``population.evaluation``
(``apply(params, hidden[B, H], obs[1, B, ...], reset[1, B]) -> (hidden, logits[1, B, A], value)``),
so a trained CNN/RNN from a run directory and the scripted partners (``stay``, ``random``) take the
same code path. Seats played by humans take their action from the browser instead.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.dynamics import transition
from ocv2.items import Static
from ocv2.render import INGREDIENT_COLORS, check_frame_size, render
from ocv2.state import State
from population import checkpoints as ckpt
from population import policy as policies
from population.config import ConfigError, load_run_config
from population.numerics import DEFAULT_PRECISION, matmul_precision

#: Cells outside a human's view window are painted this colour: the human sees what their agent sees.
HIDDEN_RGB = (24, 24, 24)
SCRIPTED_PARTNERS = ("stay", "random")


class PartnerError(ValueError):
    """A ``--partner`` that cannot be used (bad path, no checkpoint, another config's checkpoint)."""


class Partner(NamedTuple):
    """Who plays the seats no human plays."""

    kind: str  # "policy" (a trained network), "stay" / "random" (scripted) or "human" (a second browser tab)
    label: str  # what the archive's ``policies`` list says for its seats, e.g. "seed_0@update_4"
    apply: Callable  # network calling convention (see the module docstring)
    params: Any  # the policy's parameters (None for scripted partners)
    hidden_size: int  # GRU width (0 for the CNN and scripted partners)
    checkpoint: str | None = None  # the checkpoint (or exported policy) file a policy was loaded from
    run_dir: str | None = None  # the run a checkpoint belongs to (None for an exported file)
    env_kwargs: dict | None = None  # the ``ocv2.make`` arguments of the env a policy plays (its run's eval env)
    config_fingerprint: str | None = None  # the run config's fingerprint (None for an exported file)
    precision: str = DEFAULT_PRECISION  # the run.precision a policy trained with: what the game is traced at


class GameCarry(NamedTuple):
    """What the game carries from tick to tick."""

    state: State
    obs: Any  # [N, ...] every seat's observation of ``state`` (a tuple for mixed observation types)
    hidden: jax.Array  # float32[N, H] partner recurrent state per seat (unused on human seats)
    start: jax.Array  # bool[] the next step is the episode's first (the recurrent reset flag)


class StepRecord(NamedTuple):
    """One transition, as the archive stores it."""

    actions: jax.Array  # int32[N] joint action taken
    reward: jax.Array  # float32[] team reward
    shaped_reward: jax.Array  # float32[N]
    done: jax.Array  # bool[] the episode ended (max_steps reached)


class Views(NamedTuple):
    """What each human seat sees of one state."""

    frames: jax.Array  # uint8[S, H * tile, W * tile, 3] the kitchen, outside the view window hidden
    recipe_visible: jax.Array  # bool[S] a recipe indicator or active button is in view (or only one recipe exists)


class Game(NamedTuple):
    """One session's compiled functions (see ``make_game``)."""

    env: Any
    partner: Partner
    human_seats: tuple[int, ...]
    reset: Callable  # key -> GameCarry
    step: Callable  # (params, carry, human_actions int32[N], key) -> (GameCarry, StepRecord)
    views: Callable  # state -> Views


# ---------------------------------------------------------------------------------------------------
# partners
# ---------------------------------------------------------------------------------------------------


def _scripted_apply(kind: str) -> Callable:
    """A network-convention policy: always STAY, or uniformly random actions."""
    favoured = jnp.where(jnp.arange(it.NUM_ACTIONS) == it.Action.STAY, 0.0, -1e9)

    def apply(_params, hidden, obs, _reset):
        steps, batch = obs.shape[:2]
        logits = jnp.zeros((steps, batch, it.NUM_ACTIONS)) + (favoured if kind == "stay" else 0.0)
        return hidden, logits, jnp.zeros((steps, batch))

    return apply


def scripted_partner(kind: str) -> Partner:
    if kind not in SCRIPTED_PARTNERS:
        raise PartnerError(f"unknown scripted partner {kind!r}; choose one of {', '.join(SCRIPTED_PARTNERS)}")
    return Partner(kind, kind, _scripted_apply(kind), None, 0)


def human_partner() -> Partner:
    # The apply is never called (no seat is left to a policy) but keeps Game's fields uniform.
    return Partner("human", "human", _scripted_apply("stay"), None, 0)


def resolve_checkpoint(path) -> tuple[Path, int, Path]:
    """(run directory, seed, checkpoint file) for ``RUN_DIR/checkpoints/seed_<i>[/update_<n>.msgpack]``.

    A seed folder means its latest checkpoint.
    """
    path = Path(path)
    if not path.exists():
        raise PartnerError(
            f"--partner: {str(path)!r} does not exist (expected RUN_DIR/checkpoints/seed_<i>, "
            "a checkpoint file in it, an exported policy file (ocv2 export), 'human', 'stay' or 'random')"
        )
    seed_folder = path if path.is_dir() else path.parent
    seed = ckpt.seed_of_folder(seed_folder.name)
    if seed is None or seed_folder.parent.name != "checkpoints":
        hint = ""
        if path.is_dir() and (path / "checkpoints").is_dir():
            seeds = sorted(p.name for p in (path / "checkpoints").iterdir() if ckpt.seed_of_folder(p.name) is not None)
            hint = (
                f"; this looks like a run directory: pick a seed, e.g. {path / 'checkpoints' / seeds[0]}"
                if seeds
                else "; its checkpoints/ folder holds no seed"
            )
        raise PartnerError(
            f"--partner: {str(path)!r} is not RUN_DIR/checkpoints/seed_<i>, a checkpoint file "
            f"in one or an exported policy file (ocv2 export){hint}"
        )
    run_dir = seed_folder.parent.parent
    if path.is_dir():
        latest = ckpt.latest(run_dir, seed)
        if latest is None:
            raise PartnerError(f"--partner: {str(path)!r} holds no checkpoint (update_<n>.msgpack)")
        return run_dir, seed, latest
    return run_dir, seed, path


def load_policy_partner(path) -> Partner:
    """The policy of a checkpoint (or a seed's latest) or of an exported policy file (``population.policy``).

    A file that is not a run's checkpoint (``RUN_DIR/checkpoints/seed_<i>/update_<n>.msgpack``) is read as
    ``population.policy.load`` reads it, whatever its name: ``ocv2 export --out FILE`` writes any name, and
    ``render``, ``xp`` and ``population.policy.load`` take it."""
    path = Path(path)
    exported = path.is_file() and (path.suffix == policies.SUFFIX or ckpt.update_of(path) is None)
    if not exported:
        run_dir, _, path = resolve_checkpoint(path)
        if not (run_dir / "config.yaml").is_file():
            raise PartnerError(f"--partner: {str(run_dir)!r} is not an ocv2 run directory (no config.yaml)")
    try:
        policy = policies.load(path)
    except policies.PolicyError as error:
        raise PartnerError(f"--partner: {error}") from None
    try:
        precision = policies.trained_precision(policy) or DEFAULT_PRECISION
    except policies.PolicyError as error:
        raise PartnerError(f"--partner: {path}: {error}") from None
    if exported:
        return Partner(
            "policy",
            policy.name,
            policy.apply,
            policy.params,
            policy.hidden_size,
            str(path),
            env_kwargs=policy.env,
            precision=precision,
        )
    try:
        fingerprint = load_run_config(run_dir).fingerprint()  # policy.load read the same file
    except ConfigError as error:
        raise PartnerError(f"--partner: {error}") from None
    label = f"seed_{policy.meta['seed']}@update_{policy.meta['update']}"
    return Partner(
        "policy",
        label,
        policy.apply,
        policy.params,
        policy.hidden_size,
        str(path),
        str(run_dir),
        policy.env,
        fingerprint,
        precision,
    )


# ---------------------------------------------------------------------------------------------------
# the game: pure functions, jitted once by make_game
# ---------------------------------------------------------------------------------------------------


def reset_game(env, hidden_size: int, key: jax.Array) -> GameCarry:
    state = env.reset_state(key)
    hidden = jnp.zeros((env.num_agents, hidden_size), jnp.float32)
    return GameCarry(state, env.get_obs_arrays(state), hidden, jnp.array(True))


def game_step(
    env,
    apply: Callable,
    human_seats: tuple[int, ...],
    params,
    carry: GameCarry,
    human_actions: jax.Array,
    key: jax.Array,
) -> tuple[GameCarry, StepRecord]:
    """Partners act on their own observations, humans' actions are taken as given; the env steps once.

    No auto-reset: the episode ends at ``done`` and the session resets explicitly (the archive
    wants the state the last transition reached).
    """
    k_env, k_policy = jax.random.split(key)
    actions, hidden = [], []
    for seat in range(env.num_agents):
        if seat in human_seats:
            actions.append(human_actions[seat].astype(jnp.int32))
            hidden.append(carry.hidden[seat])
            continue
        h, logits, _ = apply(params, carry.hidden[seat][None], carry.obs[seat][None, None], carry.start[None, None])
        actions.append(jax.random.categorical(jax.random.fold_in(k_policy, seat), logits[0, 0]).astype(jnp.int32))
        hidden.append(h[0])
    joint = jnp.stack(actions)
    result = transition(env.config, k_env, carry.state, joint)
    carry = GameCarry(result.state, env.get_obs_arrays(result.state), jnp.stack(hidden), jnp.array(False))
    return carry, StepRecord(
        joint, result.reward.astype(jnp.float32), result.shaped_reward.astype(jnp.float32), result.state.done
    )


def seat_views(env, seats: tuple[int, ...], tile_size: int, state: State) -> Views:
    """Each seat's picture: the full render with the cells outside its agent's view window hidden."""
    image = render(state, env.layout, tile_size=tile_size)
    radius = env.config.view_radius
    rows = jnp.arange(env.height)[:, None]
    cols = jnp.arange(env.width)[None, :]
    static, timer = state.grid[:, :, 0], state.grid[:, :, 2]
    shows_recipe = (static == Static.RECIPE_INDICATOR) | ((static == Static.BUTTON) & (timer > 0))
    frames, visible = [], []
    for seat in seats:
        if radius is None:
            window = jnp.ones((env.height, env.width), bool)
        else:
            window = (jnp.abs(rows - state.agents.y[seat]) <= radius) & (jnp.abs(cols - state.agents.x[seat]) <= radius)
        pixels = jnp.repeat(jnp.repeat(window, tile_size, axis=0), tile_size, axis=1)
        frames.append(jnp.where(pixels[:, :, None], image, jnp.asarray(HIDDEN_RGB, jnp.uint8)))
        # With a single possible recipe the order is common knowledge, indicator or not.
        visible.append(jnp.any(window & shows_recipe) | (len(env.layout.possible_recipes) == 1))
    return Views(jnp.stack(frames), jnp.stack(visible))


def make_game(env, partner: Partner, human_seats, tile_size: int = 48) -> Game:
    """Jit the reset, the step and the views for this env, partner and set of human seats, each traced (and
    called) at the partner's ``precision``.

    Raises:
        ValueError: a ``tile_size`` whose frames are too big (``ocv2.render.check_frame_size``).
    """
    seats = tuple(sorted(int(s) for s in human_seats))
    check_frame_size(env.layout, int(tile_size), frames=len(seats))
    step = functools.partial(game_step, env, partner.apply, seats)
    return Game(
        env,
        partner,
        seats,
        reset=_at(partner.precision, jax.jit(functools.partial(reset_game, env, partner.hidden_size))),
        step=_at(partner.precision, jax.jit(step)),
        views=_at(partner.precision, jax.jit(functools.partial(seat_views, env, seats, int(tile_size)))),
    )


def _at(precision: str, function: Callable) -> Callable:
    """``function`` called under ``precision``'s matmul precision: a jitted function is traced (and looked up
    in its cache) under the setting in force at the call."""

    def call(*args):
        with matmul_precision(precision):
            return function(*args)

    return call


def warm_up(game: Game) -> None:
    """Compile the reset, the step and the views now (on a throwaway episode), not on the first tick."""
    carry = game.reset(jax.random.PRNGKey(0))
    stay = np.full((game.env.num_agents,), it.Action.STAY, np.int32)  # the dtype and shape every tick passes
    carry, _ = game.step(game.partner.params, carry, stay, jax.random.PRNGKey(1))
    jax.block_until_ready(game.views(carry.state))


def recipe_ingredients(code: int, num_ingredients: int) -> list[int]:
    """The ingredient indices of a recipe encoding, sorted (e.g. [0, 0, 1])."""
    counts = it.item_ingredient_counts_np(int(code), num_ingredients)
    return [i for i, count in enumerate(counts) for _ in range(count)]


def ingredient_colour(index: int) -> str:
    red, green, blue = (int(c) for c in INGREDIENT_COLORS[index % len(INGREDIENT_COLORS)])
    return f"#{red:02x}{green:02x}{blue:02x}"


def host(tree):
    """A pytree of device arrays as numpy (one transfer)."""
    return jax.tree.map(np.asarray, jax.device_get(tree))
