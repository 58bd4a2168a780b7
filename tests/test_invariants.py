"""Properties that must hold in every reachable state (hypothesis drives seeds, layouts, actions)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import ocv2
from ocv2 import items as it
from ocv2.items import Static

LAYOUTS = ["cramped_room", "grounded_coord_simple", "counter_circuit", "demo_cook_wide", "two_rooms_both"]


@functools.cache
def rollout_fn(layout: str):
    env = ocv2.make(layout, random_reset=True, max_steps=60)

    @jax.jit
    def run(key, actions):
        def body(state, xs):
            k, a = xs
            out = env.step_arrays(k, state, a)
            return out.state, out.state

        _, states = jax.lax.scan(body, env.reset_state(key), (jax.random.split(key, actions.shape[0]), actions))
        return states

    return env, run


@settings(max_examples=25, deadline=None)
@given(
    layout=st.sampled_from(LAYOUTS),
    seed=st.integers(0, 2**31 - 1),
    actions=st.lists(st.integers(0, 5), min_size=240, max_size=240),
)
def test_invariants(layout, seed, actions):
    env, run = rollout_fn(layout)
    acts = jnp.asarray(np.array(actions).reshape(120, 2), jnp.int32)
    states = run(jax.random.PRNGKey(seed), acts)
    x, y = np.asarray(states.agents.x), np.asarray(states.agents.y)
    grid = np.asarray(states.grid)
    static, items = grid[..., 0], grid[..., 1]
    # never two agents in one cell; agents only on floor
    assert ((x[:, 0] != x[:, 1]) | (y[:, 0] != y[:, 1])).all()
    assert (static[np.arange(len(x))[:, None], y, x] == Static.FLOOR).all()
    # static layer never changes
    assert (static == np.asarray(env.layout.static_objects)[None]).all()
    # items only on counters and pots
    holds = items != 0
    assert (np.isin(static[holds], [Static.WALL, Static.POT])).all()
    # at most 3 ingredients in any pot or item
    counts = np.asarray(it.ingredient_count(jnp.asarray(items)))
    assert counts.max() <= it.MAX_INGREDIENTS_IN_POT
    # timers in range
    assert grid[..., 2].min() >= 0 and grid[..., 2].max() <= it.POT_COOK_TIME
