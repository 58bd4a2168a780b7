"""Two policies playing whole episodes, keeping every transition: the data behind the trajectory archive.

``play_episodes`` (``population.evaluation``) keeps only returns and, optionally, every k-th state.
Archiving needs every state plus the actions, rewards, shaped rewards and dones of each transition,
so this module plays the same episodes and returns all of it. Pure JAX (no file formats here; the
MCAP writer is ``cluster.archive``).

Same key use and same step logic as ``play_episodes``: for one key the episodes are identical, so
returns equal ``play_episodes(...).returns`` and ``states[:, :T]`` equal its ``keep_every=1`` states
(``tests/test_archive.py`` checks this): both run ``population.evaluation.play_step``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ocv2.state import State
from population.evaluation import PolicyApply, initial_carry, play_step

__all__ = [
    "Recorded",
    "jitted_play_recorded",
    "jitted_play_recorded_pairs",
    "jitted_play_recorded_row",
    "play_recorded",
    "play_recorded_pairs",
    "play_recorded_row",
]


class Recorded(NamedTuple):
    """E whole episodes of T = ``env.max_steps`` transitions each (a leading [P] axis for pairs)."""

    states: State  # [E, T + 1, ...] s_0 (the reset state) ... s_T (the state the last transition reached)
    actions: jax.Array  # int32[E, T, N] joint action taken in s_t
    rewards: jax.Array  # float32[E, T] team (sparse) reward of transition t
    shaped_rewards: jax.Array  # float32[E, T, N]
    dones: jax.Array  # bool[E, T] transition t ended the episode (True only at t = T - 1)
    returns: jax.Array  # float32[E] sum of rewards


def play_recorded(apply: PolicyApply, hidden_size: int, env, params: tuple, key: jax.Array, episodes: int) -> Recorded:
    """One pair (one params per seat) plays ``episodes`` episodes; every transition is returned.

    The key is consumed exactly as ``play_episodes`` consumes it. Jit-compatible (``env``, ``apply``,
    ``hidden_size`` and ``episodes`` static); see ``jitted_play_recorded`` for a cached compiled copy.
    """
    carry = initial_carry(hidden_size, env, len(params), key, episodes)
    first = carry.state
    step = lambda c, x: play_step(apply, env, params, c, x)
    _, record = jax.lax.scan(step, carry, None, length=env.max_steps)
    # Episodes end only at max_steps, so the state reached by transition t is s_{t+1} of the same episode.
    states = jax.tree.map(lambda s0, later: jnp.concatenate([s0[None], later]), first, record.reached)  # [T+1, E]
    time_second = lambda x: jnp.swapaxes(x, 0, 1)
    return Recorded(
        states=jax.tree.map(time_second, states),
        actions=time_second(record.actions),
        rewards=time_second(record.reward).astype(jnp.float32),
        shaped_rewards=time_second(record.shaped_reward).astype(jnp.float32),
        dones=time_second(record.done),
        returns=jnp.sum(record.reward, axis=0).astype(jnp.float32),
    )


def play_recorded_pairs(
    apply: PolicyApply, hidden_size: int, env, params_a, params_b, keys: jax.Array, episodes: int
) -> Recorded:
    """P pairs at once: ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), keys [P]."""
    run = lambda pa, pb, k: play_recorded(apply, hidden_size, env, (pa, pb), k, episodes)
    return jax.vmap(run)(params_a, params_b, keys)


def play_recorded_row(
    apply: PolicyApply, hidden_size: int, env, params_a, params_b, key: jax.Array, episodes: int
) -> Recorded:
    """One seat-0 policy with each of P partners (``params_b`` [P]), one shared key: see ``play_row``."""
    run = lambda pb: play_recorded(apply, hidden_size, env, (params_a, pb), key, episodes)
    return jax.vmap(run)(params_b)


@functools.lru_cache(maxsize=16)
def jitted_play_recorded(apply: PolicyApply, hidden_size: int, env, episodes: int):
    """``play_recorded`` compiled once per (apply, hidden_size, env, episodes): ``f(params_pair, key)``."""
    return jax.jit(lambda params, key: play_recorded(apply, hidden_size, env, params, key, episodes))


@functools.lru_cache(maxsize=16)
def jitted_play_recorded_pairs(apply: PolicyApply, hidden_size: int, env, episodes: int):
    """``play_recorded_pairs`` compiled once per (apply, hidden_size, env, episodes): ``f(a, b, keys)``."""
    return jax.jit(lambda a, b, keys: play_recorded_pairs(apply, hidden_size, env, a, b, keys, episodes))


@functools.lru_cache(maxsize=16)
def jitted_play_recorded_row(apply: PolicyApply, hidden_size: int, env, episodes: int):
    """``play_recorded_row`` compiled once per (apply, hidden_size, env, episodes): ``f(a, b, key)``."""
    return jax.jit(lambda a, b, key: play_recorded_row(apply, hidden_size, env, a, b, key, episodes))
