"""The featurized observation equals the reference's ``get_obs_featurized`` exactly (float32).

Most states are built with numpy (random positions in each agent's room, facings, held items,
counter clutter, pot contents and timers): no env compilation per layout, so every single-ingredient
built-in layout fits in the time budget. The full env path (``random_reset`` resets and random-action
steps with ``observation_type="featurized"``) is checked against the reference env fed the same keys
and actions, and the mixed ``["default", "featurized"]`` observation against the reference's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ocv2
from ocv2 import items as it
from ocv2.featurized import PLAYER_FEATURES, SOUP, make_featurizer
from ocv2.layouts import get_layout
from ocv2.state import Agents, State
from tests.reference_adapter import actions_dict, jaxmarl_ov2, make_pair, ref_layout, state_diff, to_ref

TWO_AGENT_LAYOUTS = ["cramped_room", "asymm_advantages", "coord_ring", "forced_coord", "counter_circuit"]

# Three agents, two rooms (agent 1 alone in the right one, which has no pot): exercises the
# "other players in index order" part of the vector and unreachable targets.
THREE_AGENTS = ocv2.Layout.from_string(
    "WWPWWWBW\nO A WA W\nW A W  X\nWBWPWWOW", possible_recipes=[[0, 0, 0]], name="three_agents"
)

# Offsets of some per-player features (see the module docstring of ocv2.featurized).
HELD_SOUP, SOUP_COUNT, POT1, POT2 = 5, 16, 22, 32


# Items a random state may hold: on counters / in hands, and in pots (count 0-3, cooked or not).
_LOOSE_ITEMS = np.array([0, 0, 0, it.ingredient_unit(0), it.PLATE, SOUP, SOUP, 3 * it.ingredient_unit(0) | it.COOKED])
_POT_ITEMS = np.array([0, 1, 2, 3, 3, 3]) * it.ingredient_unit(0)


def _random_states(layout, seed: int, count: int):
    """``count`` random states of ``layout`` built with numpy (no compilation): each agent on a
    distinct floor cell of its own room with a random facing and held item; random items on
    counters; pots empty, filling, cooking (random timer) or cooked. A superset of what
    ``random_reset`` produces, so ties, held items and unreachable targets all occur."""
    rng = np.random.default_rng(seed)
    static = np.asarray(layout.static_objects)
    h, w = static.shape
    rooms = layout.room_labels
    n = layout.num_agents
    xs, ys, dirs, inv, grids = [], [], [], [], []
    for _ in range(count):
        taken = np.zeros((h, w), bool)
        x, y = [], []
        for ax, ay in layout.agent_positions:
            free = np.argwhere((rooms == rooms[ay, ax]) & ~taken)
            cy, cx = free[rng.integers(len(free))]
            taken[cy, cx] = True
            x.append(cx)
            y.append(cy)
        xs.append(x)
        ys.append(y)
        dirs.append(rng.integers(0, 4, n))
        inv.append(rng.choice(_LOOSE_ITEMS, n))
        # Clutter varies per state, from bare counters to half of them occupied.
        clutter = rng.choice([0.0, 0.05, 0.2, 0.5])
        on_counter = (static == it.Static.WALL) & (rng.random((h, w)) < clutter)
        items = np.where(on_counter, rng.choice(_LOOSE_ITEMS[3:], (h, w)), 0)
        pots = static == it.Static.POT
        pot_items = rng.choice(_POT_ITEMS, (h, w))
        cooking = (pot_items == 3 * it.ingredient_unit(0)) & (rng.random((h, w)) < 0.5)
        cooked = (pot_items == 3 * it.ingredient_unit(0)) & ~cooking & (rng.random((h, w)) < 0.5)
        items = np.where(pots, pot_items | np.where(cooked, it.COOKED, 0), items)
        timers = np.where(pots & cooking, rng.integers(1, it.POT_COOK_TIME + 1, (h, w)), 0)
        grids.append(np.stack([static, items, timers], axis=-1))
    i32 = lambda a: jnp.asarray(np.asarray(a), jnp.int32)  # noqa: E731
    return State(
        agents=Agents(x=i32(xs), y=i32(ys), dir=i32(dirs), inventory=i32(inv)),
        grid=i32(grids),
        recipe=jnp.full((count,), it.recipe_encoding_np([0, 0, 0]), jnp.int32),
        step=jnp.zeros((count,), jnp.int32),
        done=jnp.zeros((count,), bool),
        new_correct_delivery=jnp.zeros((count,), bool),
        ingredient_permutations=jnp.zeros((count, n, 1), jnp.int32),
    )


def _reference(layout, extra_agents=()):
    ref_l = ref_layout(layout)
    ref_l.agent_positions = list(ref_l.agent_positions) + list(extra_agents)
    return jaxmarl_ov2.OvercookedV2(layout=ref_l, force_path_planning=True)


def _compare(layout, states):
    featurize = make_featurizer(layout)
    assert featurize.size == 48 * layout.num_agents
    got = np.asarray(jax.jit(jax.vmap(featurize))(states))
    want = np.asarray(jax.jit(jax.vmap(_reference(layout).get_obs_featurized))(to_ref(states, False)))
    assert got.dtype == want.dtype == np.float32
    assert got.shape == want.shape == (states.step.shape[0], layout.num_agents, featurize.size)
    bad = np.flatnonzero(~np.all(got == want, axis=(1, 2)))
    assert bad.size == 0, f"{len(bad)} of {len(got)} states differ; first {bad[0]}: diff {got[bad[0]] - want[bad[0]]}"
    return got


@pytest.mark.parametrize("name", TWO_AGENT_LAYOUTS + ["three_agents"])
def test_matches_reference_on_random_states(name):
    layout = THREE_AGENTS if name == "three_agents" else get_layout(name)
    got = _compare(layout, _random_states(layout, seed=len(name), count=200))
    blocks = got[:, :, :PLAYER_FEATURES]
    # The sample is not trivial: held and lying soups, pots in every state, distances found.
    assert (blocks[..., HELD_SOUP] == 1).any()
    assert (blocks[..., SOUP_COUNT] == 3).any() and (blocks[..., SOUP_COUNT] == 0).any()
    assert (blocks[..., POT1] == 1).any()
    assert (blocks[..., POT1 + 3] == 1).any()  # a cooking pot
    assert (blocks[..., POT1 + 4] == 1).any()  # a cooked pot
    assert np.abs(blocks[..., 8:22]).max() >= 2
    if name == "forced_coord":  # agent 1 (left room) reaches no pot, agent 0 always does
        assert (blocks[:, 1, POT1 : POT1 + 10] == 0).all() and (blocks[:, 0, POT1] == 1).all()
    if name in ("asymm_advantages", "counter_circuit"):  # two pots reachable: both blocks filled
        assert (blocks[..., POT2] == 1).all()
    if name == "three_agents":  # agent 1 is alone in the pot-less right room
        assert (blocks[:, 1, POT1] == 0).all() and (blocks[:, [0, 2], POT2] == 1).all()


def test_single_agent_layout_matches_reference_player_block():
    """long_room has one agent; the reference cannot featurize it (it concatenates zero "other
    player" blocks and raises), so compare with a reference env that has a phantom second agent: a
    player's own block does not depend on the other agents (the path search ignores them)."""
    layout = get_layout("long_room")
    featurize = make_featurizer(layout)
    assert featurize.size == 48
    states = _random_states(layout, seed=1, count=200)
    phantom = (1, 1)
    b = states.step.shape[0]

    def widen(a, fill):
        return jnp.concatenate([a, jnp.full((b, 1), fill, a.dtype)], axis=1)

    ag = states.agents
    wide = states.replace(
        agents=Agents(
            x=widen(ag.x, phantom[0]), y=widen(ag.y, phantom[1]), dir=widen(ag.dir, 0), inventory=widen(ag.inventory, 0)
        ),
        ingredient_permutations=jnp.zeros((b, 2, 1), jnp.int32),
    )
    got = np.asarray(jax.jit(jax.vmap(featurize))(states))[:, 0]
    want = np.asarray(jax.jit(jax.vmap(_reference(layout, [phantom]).get_obs_featurized))(to_ref(wide, False)))[:, 0]
    np.testing.assert_array_equal(got[:, :PLAYER_FEATURES], want[:, :PLAYER_FEATURES])
    np.testing.assert_array_equal(got[:, PLAYER_FEATURES:], want[:, -2:])
    assert (got[:, HELD_SOUP] == 1).any() and (got[:, POT1 + 3] == 1).any()


def test_env_featurized_obs_match_reference_env():
    """Full env path: reset and 100 auto-resetting steps of both envs with the same keys and random
    actions (random_reset and 30-step episodes, so fresh random kitchens appear along the way)."""
    ours, ref = make_pair("cramped_room", observation_type="featurized", random_reset=True, max_steps=30)
    ours_step, ours_reset, ref_reset = jax.jit(ours.step), jax.jit(ours.reset), jax.jit(ref.reset)
    key, k_reset = jax.random.split(jax.random.PRNGKey(5))
    obs, state = ours_reset(k_reset)
    ref_obs, ref_state = ref_reset(k_reset)
    rng = np.random.default_rng(0)
    episodes = 1
    for t in range(100):
        assert state_diff(state, ref_state, 1) == [], t
        for name in ours.agents:
            a, r = np.asarray(obs[name]), np.asarray(ref_obs[name])
            assert a.dtype == r.dtype == np.float32 and a.shape == r.shape == (96,), (t, name)
            assert np.array_equal(a, r), f"step {t}, {name}: {a - r}"
        key, k_step = jax.random.split(key)
        actions = actions_dict(jnp.asarray(rng.integers(0, it.NUM_ACTIONS, ours.num_agents)), ours.agents)
        obs, state, _, dones, _ = ours_step(k_step, state, actions)
        ref_obs, ref_state, *_ = ref.step(k_step, ref_state, actions)
        episodes += bool(dones["__all__"])
    assert episodes == 4
    # More random-reset kitchens through the (already compiled) reset path.
    for k in jax.random.split(jax.random.PRNGKey(6), 40):
        (obs, _), (ref_obs, _) = ours_reset(k), ref_reset(k)
        for name in ours.agents:
            assert np.array_equal(np.asarray(obs[name]), np.asarray(ref_obs[name])), (k, name)


def test_env_mixed_observation_types_match_reference_env():
    """``["default", "featurized"]``: agent 0 gets the grid, agent 1 the vector, as the reference."""
    ours, ref = make_pair("coord_ring", observation_type=["default", "featurized"])
    layout = ours.layout
    states = _random_states(layout, seed=3, count=100)
    got = jax.jit(jax.vmap(ours.get_obs))(states)
    want = jax.jit(jax.vmap(ref.get_obs))(to_ref(states, False))
    assert (
        np.asarray(got["agent_0"]).shape == np.asarray(want["agent_0"]).shape == (100, layout.height, layout.width, 30)
    )
    assert np.array_equal(np.asarray(got["agent_0"]).astype(np.int32), np.asarray(want["agent_0"]))
    assert np.asarray(got["agent_1"]).dtype == np.asarray(want["agent_1"]).dtype == np.float32
    assert np.asarray(got["agent_1"]).shape == (100, 96)
    assert np.array_equal(np.asarray(got["agent_1"]), np.asarray(want["agent_1"]))
    # The vector is agent 1's own view (its block first), not agent 0's.
    feats = np.asarray(jax.jit(jax.vmap(make_featurizer(layout)))(states))
    assert np.array_equal(np.asarray(got["agent_1"]), feats[:, 1]) and not np.array_equal(feats[:, 0], feats[:, 1])


def test_rejects_multi_ingredient_layouts():
    layout = get_layout("cramped_room_v2")
    assert layout.num_ingredients == 2
    with pytest.raises(ValueError, match="single-ingredient"):
        make_featurizer(layout)
