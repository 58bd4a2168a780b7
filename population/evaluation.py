"""Two policies playing whole episodes together: the one rollout behind cross-play, SA collection and GIFs.

A policy is anything with the network calling convention
``apply(params, hidden [B, H], obs [1, B, ...], reset [1, B]) -> (hidden, logits [1, B, A], value)``,
so trained networks and hand-written test policies go through the same code. Every seat has its own
policy: ``apply``, ``hidden_size`` and ``greedy`` are either one value shared by all seats or a tuple
with one per seat, and ``params`` is always a tuple per seat -- so a CNN can play with an RNN, or a
policy of one run with one of another run (``population.policy``). Actions are sampled (stochastic
evaluation, as the paper) unless a seat is ``greedy`` (argmax). Episodes start from
``env.reset_state`` (no state buffer) and run exactly ``env.max_steps`` steps, the only way an
OvercookedV2 episode ends.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ocv2.state import State

PolicyApply = Callable  # (params, hidden, obs, reset) -> (hidden, logits, value)


class PairEpisodes(NamedTuple):
    """Results for P pairs x R episodes."""

    returns: jax.Array  # float32[P, R] team sparse return (shaped reward excluded)
    start_recipe: jax.Array  # int32[P, R] the recipe each episode started with (its encoding)
    states: State | None  # [P, R, S, ...] every keep_every-th state (t = 0, k, 2k, ...), or None


class PlayCarry(NamedTuple):
    """What a pair rollout carries from step to step."""

    state: State  # [R]
    obs: jax.Array  # [R, 2, ...]
    hidden: tuple  # per seat [R, H]
    start: jax.Array  # bool[R] an episode starts at this step (the recurrent reset flag)
    total: jax.Array  # float32[R] team sparse return so far
    key: jax.Array


class StepRecord(NamedTuple):
    """One transition of R environments (the scan output; unused outputs are dropped by XLA)."""

    actions: jax.Array  # int32[R, N] joint action
    reward: jax.Array  # float32[R] team reward
    shaped_reward: jax.Array  # float32[R, N]
    done: jax.Array  # bool[R]
    reached: State  # [R] the state the transition reached, before any auto-reset


def per_seat(value, num_seats: int) -> tuple:
    """``value`` for every seat: a tuple/list is taken as one entry per seat, anything else is shared."""
    if isinstance(value, (tuple, list)):
        if len(value) != num_seats:
            raise ValueError(f"expected one entry per seat ({num_seats}), got {len(value)}")
        return tuple(value)
    return (value,) * num_seats


def initial_carry(hidden_size, env, num_seats: int, key: jax.Array, episodes: int) -> PlayCarry:
    """Reset ``episodes`` environments. Resets use ``fold_in(key, 0)``, play ``fold_in(key, 1)``."""
    reset_keys = jax.random.split(jax.random.fold_in(key, 0), episodes)
    state = jax.vmap(env.reset_state)(reset_keys)
    hidden = tuple(jnp.zeros((episodes, h), jnp.float32) for h in per_seat(hidden_size, num_seats))
    return PlayCarry(
        state,
        jax.vmap(env.get_obs_arrays)(state),
        hidden,
        jnp.ones((episodes,), bool),
        jnp.zeros((episodes,), jnp.float32),
        jax.random.fold_in(key, 1),
    )


def play_step(apply, env, params: tuple, carry: PlayCarry, _unused=None, greedy=False):
    """Every seat picks an action with its own policy (sampled, or argmax if greedy); all environments step once."""
    key, k_env, *k_seats = jax.random.split(carry.key, 2 + len(params))
    applies, greedies = per_seat(apply, len(params)), per_seat(greedy, len(params))
    hidden, actions = [], []
    for seat, (p, k) in enumerate(zip(params, k_seats)):
        h, logits, _ = applies[seat](p, carry.hidden[seat], carry.obs[:, seat][None], carry.start[None])
        hidden.append(h)
        chosen = jnp.argmax(logits[0], axis=-1) if greedies[seat] else jax.random.categorical(k, logits[0])
        actions.append(chosen.astype(jnp.int32))
    joint = jnp.stack(actions, axis=1)
    keys = jax.random.split(k_env, joint.shape[0])
    out = jax.vmap(env.step_arrays)(keys, carry.state, joint)
    reward = out.reward[:, 0]
    record = StepRecord(joint, reward, out.shaped_reward, out.done, out.terminal_state)
    return PlayCarry(out.state, out.obs, tuple(hidden), out.done, carry.total + reward, key), record


def play_episodes(
    apply, hidden_size, env, params: tuple, key: jax.Array, episodes: int, keep_every: int | None = None, greedy=False
) -> PairEpisodes:
    """One pair (one params per seat) plays ``episodes`` episodes. Result arrays have P = 1 squeezed out.

    The key is consumed (see ``initial_carry``). ``apply``/``hidden_size``/``greedy``: shared or per seat.
    """
    carry = initial_carry(hidden_size, env, len(params), key, episodes)
    start_recipe = carry.state.recipe
    step = lambda c, x: play_step(apply, env, params, c, x, greedy)
    steps = env.max_steps
    if keep_every is None:
        carry, _ = jax.lax.scan(step, carry, None, length=steps)
        return PairEpisodes(carry.total, start_recipe, None)

    def chunk(c, x):  # record the state, then play keep_every steps
        recorded = c.state
        c, _ = jax.lax.scan(step, c, None, length=keep_every)
        return c, recorded

    carry, kept = jax.lax.scan(chunk, carry, None, length=steps // keep_every)
    if steps % keep_every:
        carry, _ = jax.lax.scan(step, carry, None, length=steps % keep_every)
    kept = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), kept)  # [S, R, ...] -> [R, S, ...]
    return PairEpisodes(carry.total, start_recipe, kept)


def play_seats(seats, env, key: jax.Array, episodes: int, keep_every: int | None = None, greedy=False) -> PairEpisodes:
    """``play_episodes`` for seats given as (apply, params, hidden_size) each, e.g. ``Policy.seat``."""
    applies, params, hiddens = zip(*seats)
    return play_episodes(applies, hiddens, env, tuple(params), key, episodes, keep_every, greedy)


def episode_states(seats, env, key: jax.Array, greedy=False) -> tuple[State, jax.Array]:
    """One episode of a pair, seats given as ``play_seats`` takes them: the same actions for the same key as
    ``play_seats(seats, env, key, 1)``. Returns every state from the reset one to the one the last step reached
    (before any auto-reset), [env.max_steps + 1, ...], and the episode's team sparse return (a scalar)."""
    applies, params, hiddens = zip(*seats)
    start = initial_carry(hiddens, env, len(params), key, 1)
    step = lambda c, x: play_step(applies, env, tuple(params), c, x, greedy)
    end, record = jax.lax.scan(step, start, None, length=env.max_steps)
    states = jax.tree.map(lambda first, reached: jnp.concatenate([first, reached[:, 0]]), start.state, record.reached)
    return states, end.total[0]


def play_pairs(
    apply,
    hidden_size,
    env,
    params_a,
    params_b,
    keys: jax.Array,
    episodes: int,
    keep_every: int | None = None,
    greedy=False,
) -> PairEpisodes:
    """P pairs at once: ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), keys [P]."""
    run = lambda pa, pb, k: play_episodes(apply, hidden_size, env, (pa, pb), k, episodes, keep_every, greedy)
    return jax.vmap(run)(params_a, params_b, keys)


def play_row(
    apply,
    hidden_size,
    env,
    params_a,
    params_b,
    key: jax.Array,
    episodes: int,
    keep_every: int | None = None,
    greedy=False,
) -> PairEpisodes:
    """One seat-0 policy ``params_a`` with each of P partners ``params_b`` (leading [P] axis), one shared key.

    The same episodes as ``play_pairs`` with ``params_a`` repeated P times and ``key`` repeated P times
    (identical numbers, tested), but seat 0's weights are not copied per pair: its layers run as one
    matmul over all P x R environments instead of P batched ones -- a cross-play row's shape.
    """
    run = lambda pb: play_episodes(apply, hidden_size, env, (params_a, pb), key, episodes, keep_every, greedy)
    return jax.vmap(run)(params_b)


def stack_params(params_list):
    """Stack same-shaped parameter pytrees on a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params_list)


def gather_params(stacked, indices):
    """Rows ``indices`` of stacked params (one copy per pair: only for a handful of pairs at a time)."""
    indices = jnp.asarray(indices)
    return jax.tree.map(lambda x: x[indices], stacked)
