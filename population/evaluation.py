"""Two policies playing whole episodes together: the one rollout behind cross-play, SA collection and GIFs.

A policy is anything with the network calling convention
``apply(params, hidden [B, H], obs [1, B, ...], reset [1, B]) -> (hidden, logits [1, B, A], value)``,
so trained networks and hand-written test policies go through the same code. Actions are sampled
(stochastic evaluation, as the paper). Episodes start from ``env.reset_state`` (no state buffer) and
run exactly ``env.max_steps`` steps, the only way an OvercookedV2 episode ends.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

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


def initial_carry(hidden_size: int, env, num_seats: int, key: jax.Array, episodes: int) -> PlayCarry:
    """Reset ``episodes`` environments. Resets use ``fold_in(key, 0)``, play ``fold_in(key, 1)``."""
    reset_keys = jax.random.split(jax.random.fold_in(key, 0), episodes)
    state = jax.vmap(env.reset_state)(reset_keys)
    zeros = jnp.zeros((episodes, hidden_size), jnp.float32)
    return PlayCarry(state, jax.vmap(env.get_obs_arrays)(state), (zeros,) * num_seats, jnp.ones((episodes,), bool),
                     jnp.zeros((episodes,), jnp.float32), jax.random.fold_in(key, 1))


def play_step(apply: PolicyApply, env, params: tuple, carry: PlayCarry, _unused=None):
    """Every seat samples an action from its own policy; all environments step once."""
    key, k_env, *k_seats = jax.random.split(carry.key, 2 + len(params))
    hidden, actions = [], []
    for seat, (p, k) in enumerate(zip(params, k_seats)):
        h, logits, _ = apply(p, carry.hidden[seat], carry.obs[:, seat][None], carry.start[None])
        hidden.append(h)
        actions.append(jax.random.categorical(k, logits[0]).astype(jnp.int32))
    joint = jnp.stack(actions, axis=1)
    keys = jax.random.split(k_env, joint.shape[0])
    out = jax.vmap(env.step_arrays)(keys, carry.state, joint)
    reward = out.reward[:, 0]
    record = StepRecord(joint, reward, out.shaped_reward, out.done, out.terminal_state)
    return PlayCarry(out.state, out.obs, tuple(hidden), out.done, carry.total + reward, key), record


def play_episodes(apply: PolicyApply, hidden_size: int, env, params: tuple, key: jax.Array, episodes: int,
                  keep_every: int | None = None) -> PairEpisodes:
    """One pair (one params per seat) plays ``episodes`` episodes. Result arrays have P = 1 squeezed out.

    The key is consumed (see ``initial_carry``).
    """
    carry = initial_carry(hidden_size, env, len(params), key, episodes)
    start_recipe = carry.state.recipe
    step = lambda c, x: play_step(apply, env, params, c, x)
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


def play_pairs(apply: PolicyApply, hidden_size: int, env, params_a, params_b, keys: jax.Array, episodes: int,
               keep_every: int | None = None) -> PairEpisodes:
    """P pairs at once: ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), keys [P]."""
    run = lambda pa, pb, k: play_episodes(apply, hidden_size, env, (pa, pb), k, episodes, keep_every)
    return jax.vmap(run)(params_a, params_b, keys)


def stack_params(params_list):
    """Stack same-shaped parameter pytrees on a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params_list)


def gather_params(stacked, indices):
    """Rows ``indices`` of stacked params (one copy per pair: only for a handful of pairs at a time)."""
    indices = jnp.asarray(indices)
    return jax.tree.map(lambda x: x[indices], stacked)
