"""The public API contract: types stable across reset/step, spaces that tell the truth, dict form."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ocv2


def _types(tree):
    return [
        (jax.tree_util.keystr(p), jax.typeof(x), jax.typeof(x).weak_type)
        for p, x in jax.tree_util.tree_leaves_with_path(tree)
    ]


@pytest.mark.parametrize(
    "params",
    [
        {},
        {"random_reset": True},
        {"random_agent_positions": True, "agent_view_size": 2},
        {"op_ingredient_permutations": [0, 1], "layout": "cramped_room_v2"},
    ],
)
def test_reset_and_step_states_have_identical_types(params):
    """Otherwise every jitted rollout recompiles on its second call (a weak-typed field did once)."""
    params = dict(params)
    env = ocv2.make(params.pop("layout", "cramped_room"), **params)
    state = env.reset_state(jax.random.PRNGKey(0))
    out = env.step_arrays(jax.random.PRNGKey(1), state, jnp.array([0, 5]))
    assert _types(state) == _types(out.state)
    buffered = env.reset_state(jax.random.PRNGKey(2), ocv2.stack_states([state, out.state]))
    assert _types(buffered) == _types(state)


def test_spaces_and_dict_api():
    env = ocv2.make("grounded_coord_simple", agent_view_size=2, indicate_successful_delivery=True)
    assert env.agents == ["agent_0", "agent_1"] and env.num_agents == 2 and env.num_actions == 6
    assert env.action_space("agent_0").n == 6
    space = env.observation_space("agent_1")
    assert space.shape == (5, 5, 41) and space.dtype == jnp.uint8 and space.high == 20
    obs, state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    for t in range(30):
        actions = {a: jax.random.randint(jax.random.PRNGKey(t * 2 + i), (), 0, 6) for i, a in enumerate(env.agents)}
        obs, state, rewards, dones, infos = step(jax.random.PRNGKey(100 + t), state, actions)
        for a in env.agents:
            assert space.contains(obs[a])
            assert rewards[a].dtype == jnp.float32 and infos["shaped_reward"][a].dtype == jnp.float32
        assert set(dones) == {"agent_0", "agent_1", "__all__"}
    featurized = ocv2.make("cramped_room", observation_type="featurized")
    assert featurized.observation_space().shape == (96,) and featurized.observation_space().dtype == jnp.float32


@pytest.mark.parametrize(
    "layout, params",
    [
        ("cramped_room_v2", dict(agent_view_size=1)),
        # Full view: the shared lookup plus one scatter per agent layer, in each dtype.
        ("cramped_room_v2", dict()),
        ("grounded_coord_simple", dict(op_ingredient_permutations=[0, 1, 2], indicate_successful_delivery=True)),
        ("demo_cook_wide", dict()),  # two 8-bit item chunks, C = 45 (not a multiple of 4)
    ],
)
def test_int32_observations_have_the_same_values(layout, params):
    a = ocv2.make(layout, random_reset=True, **params)
    b = ocv2.make(layout, random_reset=True, obs_dtype="int32", **params)
    for seed in range(4):
        state = a.reset_state(jax.random.PRNGKey(seed))
        oa, ob = a.get_obs_arrays(state), b.get_obs_arrays(state)
        assert oa.dtype == jnp.uint8 and ob.dtype == jnp.int32
        np.testing.assert_array_equal(np.asarray(oa, np.int32), np.asarray(ob))


def test_the_key_alone_decides_a_trajectory():
    """Compiled and step-by-step (eager) runs from the same keys agree; another key gives another trajectory."""
    env = ocv2.make("counter_circuit", random_reset=True)
    step = lambda s, k: (env.step_arrays(k, s, jax.random.randint(k, (2,), 0, 6)).state, None)

    def compiled(key):
        return jax.jit(lambda k: jax.lax.scan(step, env.reset_state(k), jax.random.split(k, 12))[0])(key)

    state = env.reset_state(jax.random.PRNGKey(9))
    for k in jax.random.split(jax.random.PRNGKey(9), 12):
        state, _ = step(state, k)
    for x, y in zip(jax.tree.leaves(compiled(jax.random.PRNGKey(9))), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    other = compiled(jax.random.PRNGKey(10))
    assert not all(
        np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(other), jax.tree.leaves(state))
    )
