"""Transition-for-transition equality with the reference, ``jaxmarl==0.2.0``.

For the same PRNG keys and actions, both envs must give equal states, observations (every channel),
rewards, shaped rewards and dones at every step, including auto-resets. Rollouts run inside one
jitted ``lax.scan`` per env so hundreds of steps x many configurations stay fast; the whole stacked
trajectories are then compared.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_adapter import MISSING_REFERENCE, make_pair, to_ours, to_ref

import ocv2

TESTS = Path(__file__).resolve().parent

STEPS = 200
SEEDS = 3
# Interact-heavy random actions reach pots, deliveries and buttons far more often than uniform ones.
ACTION_P = jnp.array([0.13, 0.13, 0.13, 0.13, 0.08, 0.40])


def _rollout(env, ours: bool, key, steps, state_buffer=None):
    """Scan ``steps`` auto-resetting steps; return stacked (state, obs, reward, shaped, done)."""
    agents = env.agents

    def reset(k):
        return env.reset(k)

    def body(carry, k):
        state = carry
        k_act, k_step = jax.random.split(k)
        acts = jax.random.choice(k_act, 6, (len(agents),), p=ACTION_P)
        actions = {a: acts[i] for i, a in enumerate(agents)}
        obs, state, rew, dones, infos = env.step(k_step, state, actions)
        out = (
            state,
            jnp.stack([obs[a].astype(jnp.int32) for a in agents]),
            jnp.stack([rew[a] for a in agents]),
            jnp.stack([infos["shaped_reward"][a] for a in agents]),
            dones["__all__"],
        )
        return state, out

    k_reset, k_steps = jax.random.split(key)
    obs0, state0 = reset(k_reset)
    _, traj = jax.lax.scan(body, state0, jax.random.split(k_steps, steps))
    obs0 = jnp.stack([obs0[a].astype(jnp.int32) for a in agents])
    return state0, obs0, traj


def compare(layout, steps=STEPS, seeds=SEEDS, ref_buffer=None, **params):
    """Run both envs from the same keys and assert every output is equal; return event counts."""
    ours, ref = make_pair(layout, ref_buffer=ref_buffer, **params)
    n = ours.layout.num_ingredients
    events = {"deliveries": 0, "shaped": 0, "buttons": 0, "cooking": 0, "resets": 0}
    run_ours = jax.jit(functools.partial(_rollout, ours, True, steps=steps))
    run_ref = jax.jit(functools.partial(_rollout, ref, False, steps=steps))
    for seed in range(seeds):
        key = jax.random.PRNGKey(seed)
        s0, o0, (st, obs, rew, shaped, done) = run_ours(key)
        rs0, ro0, (rst, robs, rrew, rshaped, rdone) = run_ref(key)
        where = f"{layout} {params} seed={seed}"
        _assert_states_equal(s0, to_ours(rs0, ours.num_agents, n), f"reset of {where}")
        np.testing.assert_array_equal(np.asarray(o0), np.asarray(ro0), err_msg=f"reset obs of {where}")
        rst = to_ours(rst, ours.num_agents, n)
        _assert_states_equal(st, rst, where)
        np.testing.assert_array_equal(np.asarray(rew), np.asarray(rrew), err_msg=f"rewards of {where}")
        np.testing.assert_array_equal(np.asarray(shaped), np.asarray(rshaped), err_msg=f"shaped rewards of {where}")
        np.testing.assert_array_equal(np.asarray(done), np.asarray(rdone), err_msg=f"dones of {where}")
        mismatch = np.argwhere(np.asarray(obs) != np.asarray(robs))
        assert mismatch.size == 0, (
            f"observations differ in {where} at [step, agent, y, x, channel] {mismatch[:5].tolist()}"
        )
        events["deliveries"] += int((np.asarray(rew) >= 20).sum())
        events["shaped"] += int((np.asarray(shaped) != 0).sum())
        events["buttons"] += int((np.asarray(rew) < 0).sum())
        events["cooking"] += int((np.asarray(st.grid)[..., 2] == 19).sum())
        events["resets"] += int(np.asarray(done).sum())
    return events


def _assert_states_equal(ours, theirs, where):
    for name in ("x", "y", "dir", "inventory"):
        np.testing.assert_array_equal(
            np.asarray(getattr(ours.agents, name)),
            np.asarray(getattr(theirs.agents, name)),
            err_msg=f"agents.{name} in {where}",
        )
    for name in ("grid", "recipe", "step", "done", "new_correct_delivery"):
        a, b = np.asarray(getattr(ours, name)), np.asarray(getattr(theirs, name))
        bad = np.argwhere(a != b)
        assert bad.size == 0, f"state.{name} differs in {where} at {bad[:5].tolist()}"


# xdist deals this file's tests out one by one after the whole-file groups (tests/conftest.py), so they fill
# the workers' gaps at the end.


# Each case compiles both envs once (most of this file's time), so every built-in layout runs exactly once:
# with a flag combination of its own where one is listed, otherwise with random full starts or random positions
# and a view radius of 2, alternately.
FLAG_CASES = [
    ("cramped_room", dict(random_reset=True, max_steps=50)),
    ("coord_ring", dict(max_steps=400)),  # episodes as long as the paper's, fixed starts
    ("asymm_advantages", dict(random_agent_positions=True, agent_view_size=2, max_steps=40)),
    (
        "cramped_room_v2",
        dict(
            random_reset=True,
            negative_rewards=True,
            sample_recipe_on_delivery=True,
            indicate_successful_delivery=True,
            agent_view_size=2,
            max_steps=60,
        ),
    ),
    (
        "grounded_coord_simple",
        dict(random_agent_positions=True, op_ingredient_permutations=[0, 1], agent_view_size=2, max_steps=80),
    ),
    ("fun_symmetries", dict(random_reset=True, op_ingredient_permutations=[0, 1, 2], max_steps=50)),
    ("counter_circuit", dict(start_cooking_interaction=True, random_reset=True, agent_view_size=1, max_steps=70)),
    (
        "test_time_simple",
        dict(
            random_reset=True,
            indicate_successful_delivery=True,
            negative_rewards=True,
            sample_recipe_on_delivery=True,
            agent_view_size=3,
            max_steps=50,
        ),
    ),
    ("demo_cook_wide", dict(random_reset=True, agent_view_size=2, start_cooking_interaction=True, max_steps=70)),
    ("grounded_coord_ring", dict(random_reset=True, agent_view_size=12, max_steps=60)),  # view larger than map
    (
        "fun_coordination",
        dict(random_reset=True, op_ingredient_permutations=[2, 3], negative_rewards=True, max_steps=60),
    ),
    ("long_room", dict(random_reset=True, max_steps=40)),  # one agent
    (
        "overcookedv2_demo",
        dict(
            random_reset=True,
            sample_recipe_on_delivery=True,
            indicate_successful_delivery=True,
            agent_view_size=1,
            max_steps=60,
        ),
    ),
    ("two_rooms_both", dict(agent_view_size=0, random_reset=True, max_steps=50)),  # 0 = whole map (reference)
]
ALL_LAYOUTS = list(ocv2.REFERENCE_LAYOUT_NAMES)
_PLAIN = [name for name in ALL_LAYOUTS if name not in {layout for layout, _ in FLAG_CASES}]
CASES = FLAG_CASES + [
    (
        name,
        dict(random_agent_positions=True, agent_view_size=2, max_steps=50)
        if i % 2
        else dict(random_reset=True, max_steps=50),
    )
    for i, name in enumerate(_PLAIN)
]


# The sweep is only meaningful if every kind of event happens in it: these cases must see them.
# (Counted here rather than in a test of their own, which would compile the same programs again.)
# Keyed by layout: each layout is exactly one case.
MUST_HAPPEN = {
    "cramped_room": ("deliveries", "cooking", "shaped", "resets"),
    "cramped_room_v2": ("buttons", "cooking", "resets"),  # with negative rewards
}


@pytest.mark.parametrize("layout,params", CASES, ids=[f"{layout}-{i}" for i, (layout, _) in enumerate(CASES)])
def test_every_layout_and_flag_combination(layout, params):
    events = compare(layout, **params)
    for kind in MUST_HAPPEN.get(layout, ()):
        assert events[kind] > 0, f"no {kind} in {layout} {params}: {events}"


def test_more_than_two_agents():
    layout = ocv2.Layout.from_string("WWPWWW\nOA AAW\nW    X\nWBWRWW", possible_recipes=[[0, 0, 0]], name="three")
    compare(layout, random_reset=True, agent_view_size=1, max_steps=50)


def test_buffer_reset_matches_reference():
    """Resets drawn from a state buffer (state augmentation) pick the same states as the reference."""
    env, ref = make_pair("cramped_room_v2", random_reset=True)
    keys = jax.random.split(jax.random.PRNGKey(7), 16)
    buffer = jax.vmap(lambda k: env.reset(k)[1])(keys)
    buffer = buffer.replace(step=buffer.step + 3)  # must be cleared by the reset
    ref_buffer = to_ref(buffer, with_permutations=False)
    compare("cramped_room_v2", ref_buffer=ref_buffer, initial_state_buffer=buffer, seeds=2, max_steps=30)
    # With other-play the buffer reset re-draws permutations from the same key as the reference.
    compare(
        "cramped_room_v2",
        ref_buffer=ref_buffer,
        initial_state_buffer=buffer,
        op_ingredient_permutations=[0, 1],
        seeds=2,
        max_steps=30,
    )


def test_mixed_observation_types_build():
    """Mixed per-agent observation types build (their values are covered in test_featurized)."""
    env = ocv2.make("cramped_room", observation_type=["default", "featurized"])
    obs, _ = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert obs["agent_0"].shape == (4, 5, 30)
    assert obs["agent_1"].ndim == 1


def test_missing_reference_fails_instead_of_skipping():
    """Without jaxmarl, importing the adapter is an error naming the test dependency (no silent skip)."""
    code = "import sys; sys.modules['jaxmarl'] = None; import reference_adapter"
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=TESTS,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(TESTS.parent)])},
    )
    assert result.returncode != 0 and MISSING_REFERENCE in result.stderr
