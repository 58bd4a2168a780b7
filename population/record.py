"""Two policies playing whole episodes, keeping every transition: the data behind the trajectory archive.

``play_episodes`` (``population.evaluation``) keeps only returns and, optionally, every k-th state.
Archiving needs every state plus the actions, rewards, shaped rewards and dones of each transition,
so this module plays the same episodes and returns all of it. Pure JAX (no file formats here; the
MCAP writer is ``cluster.archive``).

Same key use and same step logic as ``play_episodes``: for one key the episodes are identical, so
returns equal ``play_episodes(...).returns`` and ``states[:, :T]`` equal its ``keep_every=1`` states
(``tests/test_archive.py`` checks this). The per-step policy/env logic below repeats
``population.evaluation._step`` (about ten lines) because that function drops the actions; keep them
in step.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ocv2.state import State
from population.evaluation import PolicyApply

__all__ = ["Recorded", "jitted_play_recorded", "jitted_play_recorded_pairs", "play_recorded", "play_recorded_pairs"]


class Recorded(NamedTuple):
    """E whole episodes of T = ``env.max_steps`` transitions each (a leading [P] axis for pairs)."""

    states: State  # [E, T + 1, ...] s_0 (the reset state) ... s_T (the state the last transition reached)
    actions: jax.Array  # int32[E, T, N] joint action taken in s_t
    rewards: jax.Array  # float32[E, T] team (sparse) reward of transition t
    shaped_rewards: jax.Array  # float32[E, T, N]
    dones: jax.Array  # bool[E, T] transition t ended the episode (True only at t = T - 1)
    returns: jax.Array  # float32[E] sum of rewards


class _Carry(NamedTuple):
    state: State  # [E]
    obs: jax.Array  # [E, N, ...]
    hidden: tuple  # per seat [E, H]
    start: jax.Array  # bool[E] (the recurrent reset flag)
    key: jax.Array


def _step(apply: PolicyApply, env, params: tuple, carry: _Carry, _unused):
    # Mirrors population.evaluation._step (same key splits), and also returns the transition.
    key, k_env, *k_seats = jax.random.split(carry.key, 2 + len(params))
    hidden, actions = [], []
    for seat, (p, k) in enumerate(zip(params, k_seats)):
        h, logits, _ = apply(p, carry.hidden[seat], carry.obs[:, seat][None], carry.start[None])
        hidden.append(h)
        actions.append(jax.random.categorical(k, logits[0]).astype(jnp.int32))
    joint = jnp.stack(actions, axis=1)
    keys = jax.random.split(k_env, joint.shape[0])
    out = jax.vmap(env.step_arrays)(keys, carry.state, joint)
    transition = (joint, out.reward[:, 0], out.shaped_reward, out.done, out.terminal_state)
    return _Carry(out.state, out.obs, tuple(hidden), out.done, key), transition


def play_recorded(apply: PolicyApply, hidden_size: int, env, params: tuple, key: jax.Array,
                  episodes: int) -> Recorded:
    """One pair (one params per seat) plays ``episodes`` episodes; every transition is returned.

    The key is consumed exactly as ``play_episodes`` consumes it. Jit-compatible (``env``, ``apply``,
    ``hidden_size`` and ``episodes`` static); see ``jitted_play_recorded`` for a cached compiled copy.
    """
    reset_keys = jax.random.split(jax.random.fold_in(key, 0), episodes)
    state = jax.vmap(env.reset_state)(reset_keys)
    obs = jax.vmap(env.get_obs_arrays)(state)
    zeros = jnp.zeros((episodes, hidden_size), jnp.float32)
    carry = _Carry(state, obs, (zeros,) * len(params), jnp.ones((episodes,), bool), jax.random.fold_in(key, 1))
    step = lambda c, x: _step(apply, env, params, c, x)
    _, (actions, rewards, shaped, dones, reached) = jax.lax.scan(step, carry, None, length=env.max_steps)
    # Episodes end only at max_steps, so the state reached by transition t is s_{t+1} of the same episode.
    states = jax.tree.map(lambda first, later: jnp.concatenate([first[None], later]), state, reached)  # [T+1, E]
    time_second = lambda x: jnp.swapaxes(x, 0, 1)
    return Recorded(
        states=jax.tree.map(time_second, states),
        actions=time_second(actions),
        rewards=time_second(rewards).astype(jnp.float32),
        shaped_rewards=time_second(shaped).astype(jnp.float32),
        dones=time_second(dones),
        returns=jnp.sum(rewards, axis=0).astype(jnp.float32),
    )


def play_recorded_pairs(apply: PolicyApply, hidden_size: int, env, params_a, params_b, keys: jax.Array,
                        episodes: int) -> Recorded:
    """P pairs at once: ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), keys [P]."""
    run = lambda pa, pb, k: play_recorded(apply, hidden_size, env, (pa, pb), k, episodes)
    return jax.vmap(run)(params_a, params_b, keys)


@functools.lru_cache(maxsize=16)
def jitted_play_recorded(apply: PolicyApply, hidden_size: int, env, episodes: int):
    """``play_recorded`` compiled once per (apply, hidden_size, env, episodes): ``f(params_pair, key)``."""
    return jax.jit(lambda params, key: play_recorded(apply, hidden_size, env, params, key, episodes))


@functools.lru_cache(maxsize=16)
def jitted_play_recorded_pairs(apply: PolicyApply, hidden_size: int, env, episodes: int):
    """``play_recorded_pairs`` compiled once per (apply, hidden_size, env, episodes): ``f(a, b, keys)``."""
    return jax.jit(lambda a, b, keys: play_recorded_pairs(apply, hidden_size, env, a, b, keys, episodes))
