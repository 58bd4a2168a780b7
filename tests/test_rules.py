"""Targeted tests of single rules: the reference's interaction table, movement, timers, flags.

States are built by hand on a small kitchen so each test shows one rule in isolation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import ocv2
from ocv2 import items as it
from ocv2.dynamics import tick_timers, transition
from ocv2.items import Action, Direction, Static

KITCHEN = """
WW0WPWW
B A  AX
L     W
WWRWWWW
"""
R, D, L, U, S, I = (Action.RIGHT, Action.DOWN, Action.LEFT, Action.UP, Action.STAY, Action.INTERACT)
ONION = it.ingredient_unit(0)
SOUP = 3 * ONION  # recipe [0, 0, 0]
DISH = SOUP | it.PLATE | it.COOKED


def kitchen(**params):
    layout = ocv2.Layout.from_string(KITCHEN, possible_recipes=[[0, 0, 0]], name="kitchen")
    return ocv2.make(layout, **params)


def start(env, key=0):
    return env.reset_state(jax.random.PRNGKey(key))


def place(state, agent, x, y, direction, inventory=0):
    a = state.agents
    return state.replace(
        agents=a.replace(
            x=a.x.at[agent].set(x),
            y=a.y.at[agent].set(y),
            dir=a.dir.at[agent].set(direction),
            inventory=a.inventory.at[agent].set(inventory),
        )
    )


def set_cell(state, x, y, item=None, timer=None):
    grid = state.grid
    if item is not None:
        grid = grid.at[y, x, 1].set(item)
    if timer is not None:
        grid = grid.at[y, x, 2].set(timer)
    return state.replace(grid=grid)


def act(env, state, *actions, key=0):
    return transition(env.config, jax.random.PRNGKey(key), state, jnp.array(actions, jnp.int32))


def park_agent_1(state):
    """Agent 1 out of the way, facing the floor."""
    return place(state, 1, 5, 2, Direction.LEFT)


# ---------------------------------------------------------------- interaction table
def test_row1_ingredient_pile_gives_ingredient():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 2, 1, Direction.UP))  # pile '0' above (2, 0)
    out = act(env, s, I, S)
    assert int(out.state.agents.inventory[0]) == ONION
    full = place(s, 0, 2, 1, Direction.UP, inventory=it.PLATE)
    assert int(act(env, full, I, S).state.agents.inventory[0]) == it.PLATE  # hands full: nothing


def test_row2_plate_pile_and_plate_pickup_rule():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 1, 1, Direction.LEFT))  # plate pile at (0, 1)
    out = act(env, s, I, S)
    assert int(out.state.agents.inventory[0]) == it.PLATE
    assert float(out.shaped_reward[0]) == 0.0  # no non-empty pot -> no plate-pickup reward
    busy = set_cell(s, 4, 0, item=ONION)
    assert float(act(env, busy, I, S).shaped_reward[0]) == it.SHAPED_PLATE_PICKUP
    blocked = set_cell(busy, 6, 2, item=it.PLATE)  # a bare plate on any counter blocks the reward
    assert float(act(env, blocked, I, S).shaped_reward[0]) == 0.0


def test_plate_pickup_uses_start_of_step_inventories():
    """Two agents taking plates in the same step with one non-empty pot are both paid (reference)."""
    layout = ocv2.Layout.from_string("WWPWW\nBA AB\nWW0RW", possible_recipes=[[0, 0, 0]], name="plates")
    env = ocv2.make(layout)
    s = place(place(start(env), 0, 1, 1, Direction.LEFT), 1, 3, 1, Direction.RIGHT)
    s = set_cell(s, 2, 0, item=ONION)
    out = act(env, s, I, I)
    assert out.state.agents.inventory.tolist() == [it.PLATE, it.PLATE]
    assert out.shaped_reward.tolist() == [it.SHAPED_PLATE_PICKUP, it.SHAPED_PLATE_PICKUP]


def test_row3_and_row4_counter_pickup_and_drop():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 1, 2, Direction.DOWN, inventory=ONION))  # (1, 3) is a counter
    out = act(env, s, I, S)
    assert int(out.state.grid[3, 1, 1]) == ONION and int(out.state.agents.inventory[0]) == 0
    back = act(env, out.state, I, S)
    assert int(back.state.grid[3, 1, 1]) == 0 and int(back.state.agents.inventory[0]) == ONION
    occupied = set_cell(s, 1, 3, item=it.PLATE)  # full counter, full hands: nothing
    out = act(env, occupied, I, S)
    assert int(out.state.grid[3, 1, 1]) == it.PLATE and int(out.state.agents.inventory[0]) == ONION


def test_row5_pot_placement_auto_cook_and_shaped_reward():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 4, 1, Direction.UP, inventory=ONION))  # pot at (4, 0)
    s = set_cell(s, 4, 0, item=2 * ONION)
    out = act(env, s, I, S)
    assert int(out.state.grid[0, 4, 1]) == SOUP
    assert int(out.state.grid[0, 4, 2]) == it.POT_COOK_TIME - 1  # started and ticked in the same step
    assert float(out.shaped_reward[0]) == it.SHAPED_PLACEMENT_IN_POT
    # A fourth ingredient cannot go in a cooking pot.
    again = place(out.state, 0, 4, 1, Direction.UP, inventory=ONION)
    assert int(act(env, again, I, S).state.agents.inventory[0]) == ONION


def test_placement_reward_only_when_useful_and_never_negative_by_default():
    layout = ocv2.Layout.from_string("WWPWW\n0A A1\nW   R\nWBWXW", possible_recipes=[[0, 0, 0]], name="two")
    env = ocv2.make(layout, negative_rewards=True)
    s = place(start(env), 0, 2, 1, Direction.UP, inventory=it.ingredient_unit(1))
    s = place(s, 1, 3, 2, Direction.DOWN)
    assert float(act(env, s, I, S).shaped_reward[0]) == 0.0  # useless ingredient: 0, not -3 (reference)
    fixed = ocv2.make(layout, negative_rewards=True, fix_negative_placement_reward=True)
    assert float(act(fixed, s, I, S).shaped_reward[0]) == -it.SHAPED_PLACEMENT_IN_POT


def test_row6_start_cooking_interaction():
    env = kitchen(start_cooking_interaction=True)
    s = park_agent_1(place(start(env), 0, 4, 1, Direction.UP, inventory=ONION))
    s = set_cell(s, 4, 0, item=2 * ONION)
    out = act(env, s, I, S)
    assert int(out.state.grid[0, 4, 2]) == 0  # full but not cooking: needs an interaction
    started = act(env, place(out.state, 0, 4, 1, Direction.UP), I, S)
    assert int(started.state.grid[0, 4, 2]) == it.POT_COOK_TIME - 1
    assert float(started.shaped_reward[0]) == it.SHAPED_POT_START_COOKING
    partial = act(env, set_cell(place(s, 0, 4, 1, Direction.UP), 4, 0, item=ONION), I, S)
    assert int(partial.state.grid[0, 4, 2]) == it.POT_COOK_TIME - 1  # one-onion soup allowed (reference)
    assert float(partial.shaped_reward[0]) == 0.0


def test_row7_dish_pickup():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 4, 1, Direction.UP, inventory=it.PLATE))
    s = set_cell(s, 4, 0, item=SOUP | it.COOKED)
    out = act(env, s, I, S)
    assert int(out.state.agents.inventory[0]) == DISH and int(out.state.grid[0, 4, 1]) == 0
    assert float(out.shaped_reward[0]) == it.SHAPED_DISH_PICKUP


def test_row8_delivery_rewards_and_flag():
    env = kitchen(negative_rewards=True, indicate_successful_delivery=True)
    s = park_agent_1(place(start(env), 0, 5, 1, Direction.RIGHT, inventory=DISH))  # goal at (6, 1)
    s = place(s, 1, 1, 2, Direction.LEFT)
    out = act(env, s, I, S)
    assert float(out.reward) == it.DELIVERY_REWARD and bool(out.correct_delivery)
    assert bool(out.state.new_correct_delivery) and int(out.state.agents.inventory[0]) == 0
    obs = env.get_obs_arrays(out.state)
    assert int(obs[0, 1, 6, -1]) == 1  # delivery channel lit at the goal for one observation
    later = act(env, out.state, S, S)
    assert not bool(later.state.new_correct_delivery)
    wrong = place(s, 0, 5, 1, Direction.RIGHT, inventory=it.PLATE | it.COOKED | ONION)
    out = act(env, wrong, I, S)
    assert float(out.reward) == -it.DELIVERY_REWARD and not bool(out.correct_delivery)
    assert float(act(kitchen(), wrong, I, S).reward) == 0.0  # without negative rewards


def test_row9_button_timer_cost_and_repress():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 1, 2, Direction.LEFT))  # button 'L' at (0, 2)
    out = act(env, s, I, S)
    assert float(out.reward) == -it.BUTTON_COST and int(out.state.grid[2, 0, 2]) == it.BUTTON_ACTIVE_TIME - 1
    visible = []
    state = out.state
    for _ in range(10):
        visible.append(int(env.get_obs_arrays(state)[0, 2, 0].sum() > 1))
        state = act(env, state, S, S).state
    assert sum(visible) == it.BUTTON_ACTIVE_TIME - 1  # recipe shown for 9 observations (reference)
    again = act(env, out.state, I, S)
    assert float(again.reward) == -it.BUTTON_COST  # re-press re-arms and charges again (reference)
    fixed = kitchen(fix_button_repress=True)
    again = act(fixed, out.state, I, S)
    assert float(again.reward) == 0.0 and int(again.state.grid[2, 0, 2]) == it.BUTTON_ACTIVE_TIME - 2


def test_row10_random_reset_full_idle_pot_starts_on_any_interaction():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 4, 1, Direction.UP, inventory=it.PLATE))
    s = set_cell(s, 4, 0, item=SOUP, timer=0)
    out = act(env, s, I, S)
    assert int(out.state.grid[0, 4, 2]) == it.POT_COOK_TIME - 1 and int(out.state.agents.inventory[0]) == it.PLATE


def test_sequential_interactions_see_earlier_changes():
    """Agent 0 takes the onion off a counter; agent 1 then drops its plate on the freed counter."""
    layout = ocv2.Layout.from_string("WWPWW\n0AWAX\nW   W\nWBWRW", possible_recipes=[[0, 0, 0]], name="seq")
    env = ocv2.make(layout)
    s = place(place(start(env), 0, 1, 1, Direction.RIGHT), 1, 3, 1, Direction.LEFT, inventory=it.PLATE)
    s = set_cell(s, 2, 1, item=ONION)
    out = act(env, s, I, I)
    assert out.state.agents.inventory.tolist() == [ONION, 0]
    assert int(out.state.grid[1, 2, 1]) == it.PLATE


# ---------------------------------------------------------------- movement
def test_moves_collisions_and_swaps():
    env = kitchen()
    s = place(place(start(env), 0, 2, 1, Direction.UP), 1, 4, 1, Direction.UP)
    out = act(env, s, R, L)  # both target (3, 1): both stay, but turn
    assert out.state.agents.x.tolist() == [2, 4] and out.state.agents.dir.tolist() == [Direction.RIGHT, Direction.LEFT]
    s = place(place(start(env), 0, 2, 1, Direction.UP), 1, 3, 1, Direction.UP)
    out = act(env, s, R, L)  # swap: both stay
    assert out.state.agents.x.tolist() == [2, 3]
    out = act(env, s, R, R)  # follow the leader: allowed
    assert out.state.agents.x.tolist() == [3, 4]
    out = act(env, s, R, S)  # into a standing agent: stays
    assert out.state.agents.x.tolist() == [2, 3]
    out = act(env, s, U, S)  # into a pile: stays, turns
    assert out.state.agents.y.tolist() == [1, 1] and int(out.state.agents.dir[0]) == Direction.UP


def test_pot_timer_finishes_after_twenty_transitions():
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 4, 1, Direction.UP, inventory=ONION))
    s = set_cell(s, 4, 0, item=2 * ONION)
    state = act(env, s, I, S).state
    for step in range(1, 20):
        assert not int(state.grid[0, 4, 1]) & it.COOKED, step
        state = act(env, state, S, S).state
    assert int(state.grid[0, 4, 1]) == SOUP | it.COOKED and int(state.grid[0, 4, 2]) == 0


def test_episode_ends_at_max_steps_and_auto_resets():
    env = ocv2.make("cramped_room", max_steps=5)
    step = jax.jit(env.step_arrays)
    state = start(env)
    for t in range(5):
        out = step(jax.random.PRNGKey(t), state, jnp.array([S, S]))
        state = out.state
    assert bool(out.done) and int(out.terminal_state.step) == 5 and int(out.state.step) == 0


def test_recipe_resampling_on_delivery():
    layout = ocv2.Layout.from_string("WWPWW\n0A AX\nW   R\nWBW1W", name="resample")
    env = ocv2.make(layout, sample_recipe_on_delivery=True)
    s = start(env)
    recipes = set()
    for k in range(12):
        s2 = s.replace(recipe=jnp.int32(12))
        s2 = place(place(s2, 0, 3, 1, Direction.RIGHT, inventory=12 | it.PLATE | it.COOKED), 1, 1, 1, Direction.UP)
        out = act(env, s2, I, S, key=k)
        assert float(out.reward) == it.DELIVERY_REWARD
        recipes.add(int(out.state.recipe))
    assert len(recipes) > 1  # re-drawn (sometimes the same one again, as the reference)
    assert recipes <= {int(it.recipe_encoding_np(r)) for r in env.layout.possible_recipes}
    no = act(
        ocv2.make(layout),
        place(
            place(s.replace(recipe=jnp.int32(12)), 0, 3, 1, Direction.RIGHT, inventory=12 | it.PLATE | it.COOKED),
            1,
            1,
            1,
            Direction.UP,
        ),
        I,
        S,
    )
    assert int(no.state.recipe) == 12


# ---------------------------------------------------------------- other-play and buffers
def test_op_permutes_each_agents_view_only():
    env = ocv2.make("grounded_coord_simple", op_ingredient_permutations=[0, 1])
    plain = ocv2.make("grounded_coord_simple")
    seen = set()
    for k in range(20):
        state = env.reset_state(jax.random.PRNGKey(k))
        perms = np.asarray(state.ingredient_permutations)
        seen.add(tuple(perms.reshape(-1)))
        assert sorted(perms[0][:2].tolist()) == [0, 1] and perms[0][2] == 2
        obs, base = env.get_obs_arrays(state), plain.get_obs_arrays(state)
        n = 3
        pile = 20 + 2 * n
        for a in range(2):
            m = perms[a]
            np.testing.assert_array_equal(np.asarray(obs[a][..., pile : pile + n]), np.asarray(base[a][..., pile + m]))
        # dynamics are not permuted
        acts = jnp.array([I, I])
        np.testing.assert_array_equal(
            np.asarray(act(env, state, *acts).state.grid), np.asarray(act(plain, state, *acts).state.grid)
        )
    assert len(seen) > 1


def test_buffer_reset_draws_buffer_states_and_clears_episode_fields():
    env = ocv2.make("cramped_room", random_reset=True)
    buffer = ocv2.stack_states([env.reset_state(jax.random.PRNGKey(k)).replace(step=jnp.int32(9)) for k in range(5)])
    buffered = ocv2.make("cramped_room", initial_state_buffer=buffer)
    grids = {np.asarray(buffer.grid[i]).tobytes() for i in range(5)}
    for k in range(10):
        state = buffered.reset_state(jax.random.PRNGKey(k))
        assert np.asarray(state.grid).tobytes() in grids and int(state.step) == 0
    # The same buffer can be passed per call (traced), without rebuilding the env.
    state = jax.jit(env.reset_state)(jax.random.PRNGKey(3), buffer)
    assert np.asarray(state.grid).tobytes() in grids
    _, from_state = env.reset_from_state(jax.random.PRNGKey(0), jax.tree.map(lambda x: x[2], buffer))
    np.testing.assert_array_equal(np.asarray(from_state.grid), np.asarray(buffer.grid[2]))


def test_offmap_interaction_wraps_by_default_and_fix_blocks_it():
    """Reachable only from a hand-made state: an agent on the edge facing outwards."""
    env = kitchen()
    s = park_agent_1(place(start(env), 0, 0, 1, Direction.LEFT))  # stands on the plate-pile column
    s = s.replace(grid=s.grid.at[1, 0, 0].set(Static.FLOOR))
    out = act(env, s, I, S)  # x = -1 wraps to the goal column (6, 1): nothing to deliver, but reads it
    assert int(out.state.agents.inventory[0]) == 0
    s = set_cell(s.replace(grid=s.grid.at[1, 6, 0].set(Static.WALL)), 6, 1, item=ONION)
    assert int(act(env, s, I, S).state.agents.inventory[0]) == ONION  # picked up across the map
    fixed = kitchen(fix_offmap_interaction=True)
    assert int(act(fixed, s, I, S).state.agents.inventory[0]) == 0


def test_zero_view_size():
    assert ocv2.make("cramped_room", agent_view_size=0).obs_shape == (4, 5, 30)  # reference: whole map
    assert ocv2.make("cramped_room", agent_view_size=0, fix_zero_view_size=True).obs_shape == (1, 1, 30)


def test_paper_obs_truncation_drops_last_channels():
    env = ocv2.make("grounded_coord_simple", agent_view_size=2, paper_obs_truncation=True)
    full = ocv2.make("grounded_coord_simple", agent_view_size=2)
    assert env.obs_shape == (5, 5, 38) and full.obs_shape == (5, 5, 40)
    state = start(full)
    np.testing.assert_array_equal(
        np.asarray(env.get_obs_arrays(state)), np.asarray(full.get_obs_arrays(state))[..., :38]
    )
    assert (
        ocv2.make(
            "test_time_wide", agent_view_size=2, indicate_successful_delivery=True, paper_obs_truncation=True
        ).obs_shape[-1]
        == 43
    )
    assert ocv2.make("cramped_room", paper_obs_truncation=True, agent_view_size=2).obs_shape[-1] == 30


def test_action_and_direction_lookups_match_their_tables():
    # The select-chain lookups (used instead of gathers from constant arrays) must equal the tables.
    actions = jnp.arange(it.NUM_ACTIONS)
    np.testing.assert_array_equal(np.asarray(it.action_direction(actions)), it.ACTION_DIRECTION)
    dx, dy = it.direction_vector(jnp.arange(len(Direction)))
    np.testing.assert_array_equal(np.stack([np.asarray(dx), np.asarray(dy)], axis=1), it.DIRECTION_VECTORS)


def test_tick_timers_counts_pots_and_buttons_down():
    grid = np.zeros((1, 6, 3), np.int32)
    grid[0, :, 0] = [Static.POT, Static.POT, Static.POT, Static.BUTTON, Static.BUTTON, Static.WALL]
    grid[0, :, 1] = [it.ingredient_unit(0)] * 3 + [0, 0, it.PLATE]
    grid[0, :, 2] = [5, 1, 0, 3, -2, 7]  # cooking, finishing, idle, active button, negative button, counter
    out = np.asarray(tick_timers(jnp.asarray(grid)))
    np.testing.assert_array_equal(out[0, :, 0], grid[0, :, 0])
    np.testing.assert_array_equal(out[0, :, 2], [4, 0, 0, 2, 0, 7])
    np.testing.assert_array_equal(
        out[0, :, 1], [grid[0, 0, 1], grid[0, 1, 1] | it.COOKED, grid[0, 2, 1], 0, 0, it.PLATE]
    )
