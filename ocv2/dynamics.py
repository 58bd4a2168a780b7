"""One transition of the kitchen: movement, collisions, interactions, timers, recipe resampling.

Pure functions of (config, key, state, actions). ``actions`` is int32[N]. The order of sub-steps and
every arithmetic detail follow the reference (JaxMARL 0.2.0), including its quirks; the fixes
are switched on by ``EnvConfig.fix_*`` flags.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ocv2 import items as it
from ocv2.config import EnvConfig
from ocv2.items import Action, Static
from ocv2.state import Agents, State


class Transition(NamedTuple):
    """What one transition produced (before observations and auto-reset)."""

    state: State
    reward: jax.Array  # float32[] team reward
    shaped_reward: jax.Array  # float32[N]
    correct_delivery: jax.Array  # bool[]


def sample_recipe(config: EnvConfig, key: jax.Array) -> jax.Array:
    """Draw one of the layout's recipes uniformly (key consumed)."""
    recipes = jnp.asarray(config.layout.possible_recipes, dtype=jnp.int32)
    if recipes.shape[0] == 1:
        # randint over one value is always 0: skip the draw (a threefry hash per env, and a reset
        # state is drawn every step for auto-reset).
        return it.recipe_encoding(recipes[0])
    index = jax.random.randint(key, (), 0, recipes.shape[0])
    return it.recipe_encoding(recipes[index])


def move_agents(state: State, actions: jax.Array) -> Agents:
    """Simultaneous moves with collision resolution and swap prevention, in the reference's order."""
    agents = state.agents
    height, width = state.grid.shape[:2]
    num_agents = agents.x.shape[0]
    act_dir = it.action_direction(actions)
    moving = act_dir >= 0
    dx, dy = it.direction_vector(jnp.maximum(act_dir, 0))
    tx = jnp.clip(agents.x + dx, 0, width - 1)
    ty = jnp.clip(agents.y + dy, 0, height - 1)
    free = state.grid[ty, tx, 0] == Static.FLOOR
    new_x = jnp.where(moving & free, tx, agents.x)
    new_y = jnp.where(moving & free, ty, agents.y)
    direction = jnp.where(moving, act_dir, agents.dir)

    # Agents are Python lists of scalars here (N is small and static), so every pairwise test stays
    # elementwise. An [N, N] matrix reduced over an axis ended an XLA fusion at each reduction; at
    # batch 1, where a step is a few dozen kernels, that cost ~8 % of the whole step.
    ids = range(num_agents)
    old_x, old_y, want_x, want_y = list(agents.x), list(agents.y), list(new_x), list(new_y)

    # Revert every agent standing on a shared cell until no cell is shared. Each round reverts at
    # least one more agent (start cells are distinct), so N rounds always reach the fixed point.
    reverted = [jnp.zeros((), bool) for _ in ids]
    for _ in ids:
        px = [jnp.where(reverted[i], old_x[i], want_x[i]) for i in ids]
        py = [jnp.where(reverted[i], old_y[i], want_y[i]) for i in ids]
        reverted = [_any(reverted[i], *((px[i] == px[j]) & (py[i] == py[j]) for j in ids if j != i)) for i in ids]
    px = [jnp.where(reverted[i], old_x[i], want_x[i]) for i in ids]
    py = [jnp.where(reverted[i], old_y[i], want_y[i]) for i in ids]

    # One pass of swap prevention: i took j's cell and j took i's -> both stay.
    def took(i, j):
        return (px[i] == old_x[j]) & (py[i] == old_y[j])

    swapped = [_any(*(took(i, j) & took(j, i) for j in ids if j != i)) for i in ids]
    px = jnp.stack([jnp.where(swapped[i], old_x[i], px[i]) for i in ids])
    py = jnp.stack([jnp.where(swapped[i], old_y[i], py[i]) for i in ids])
    return agents.replace(x=px, y=py, dir=direction)


def _any(*flags) -> jax.Array:
    """OR of a few boolean scalars (elementwise, where ``jnp.any`` would be a reduction)."""
    out = jnp.zeros((), bool)
    for flag in flags:
        out = out | flag
    return out


class _Interaction(NamedTuple):
    cell: jax.Array  # int32[3] new content of the facing cell
    inventory: jax.Array
    reward: jax.Array
    shaped: jax.Array
    correct_delivery: jax.Array


class _PlateCounts(NamedTuple):
    """What the plate-pickup bonus looks at: plates held at the step start, and over the grid as it is
    when the agent acts (earlier agents' interactions applied) the non-empty pots and bare plates."""

    plates_held: jax.Array
    busy_pots: jax.Array
    loose_plates: jax.Array


def _busy_pot(cell) -> jax.Array:
    return (cell[..., 0] == Static.POT) & (cell[..., 1] != 0)


def plate_counts(grid: jax.Array, inventories: jax.Array) -> _PlateCounts:
    return _PlateCounts(
        # Summed per agent (elementwise), not reduced: see move_agents.
        plates_held=sum((inventories[a] == it.PLATE).astype(jnp.int32) for a in range(inventories.shape[0])),
        busy_pots=jnp.sum(_busy_pot(grid)),
        loose_plates=jnp.sum(grid[:, :, 1] == it.PLATE),
    )


def interact(config: EnvConfig, cell, inventory, recipe, counts: _PlateCounts) -> _Interaction:
    """Result of one agent interacting with the cell it faces (the reference's interaction table)."""
    static, item, timer = cell[0], cell[1], cell[2]
    plated_recipe = recipe | it.PLATE | it.COOKED
    is_plate_pile = static == Static.PLATE_PILE
    is_ingredient_pile = static >= Static.INGREDIENT_PILE
    is_pile = is_plate_pile | is_ingredient_pile
    is_pot = static == Static.POT
    is_goal = static == Static.GOAL
    is_counter = static == Static.WALL
    is_button = static == Static.BUTTON

    cell_empty = item == 0
    hands_empty = inventory == 0
    holds_raw = it.is_raw_ingredient(inventory)
    holds_plate = inventory == it.PLATE
    holds_dish = (inventory & it.COOKED) != 0
    combined = item + inventory  # items combine by addition (pot + ingredient, pot + plate)

    cooking = is_pot & (timer > 0)
    cooked = is_pot & ((item & it.COOKED) != 0)
    idle = is_pot & ~cooking & ~cooked

    take_dish = cooked & holds_plate
    shaped = jnp.where(take_dish & (combined == plated_recipe), float(it.SHAPED_DISH_PICKUP), 0.0)

    pickup = (is_pile & hands_empty) | take_dish | (is_counter & ~cell_empty & hands_empty)
    press = is_button & hands_empty & cell_empty
    if config.fix_button_repress:
        press = press & (timer == 0)

    place = idle & holds_raw & (it.ingredient_count(item) != it.MAX_INGREDIENTS_IN_POT)
    field = inventory | (inventory << 1)  # the 2-bit counter of the held ingredient
    useful = (item & field) < (recipe & field)
    placement_reward = jnp.where(useful, float(it.SHAPED_PLACEMENT_IN_POT), 0.0)
    if config.fix_negative_placement_reward and config.negative_rewards:
        placement_reward = jnp.where(useful, placement_reward, -float(it.SHAPED_PLACEMENT_IN_POT))
    # Reference quirk (default): the sign is chosen after multiplying by "useful", so never -3.
    shaped = shaped + jnp.where(place, placement_reward, 0.0)

    drop = (is_counter & cell_empty & ~hands_empty) | place
    deliver = is_goal & holds_dish
    no_effect = ~pickup & ~drop & ~deliver

    pile_item = jnp.where(is_plate_pile, it.PLATE, 0) + jnp.where(
        is_ingredient_pile, it.ingredient_unit(jnp.maximum(static - Static.INGREDIENT_PILE, 0)), 0
    )
    new_item = jnp.where(drop, combined, 0) + jnp.where(no_effect, item, 0)

    start_cooking = idle & ~cell_empty & hands_empty & config.start_cooking_interaction
    shaped = shaped + jnp.where(start_cooking & (item == recipe), float(it.SHAPED_POT_START_COOKING), 0.0)
    full_now = it.ingredient_count(new_item) == it.MAX_INGREDIENTS_IN_POT
    auto_cook = idle & full_now & (not config.start_cooking_interaction)
    starts_timer = start_cooking | auto_cook
    new_timer = jnp.where(starts_timer, it.POT_COOK_TIME, jnp.where(press, it.BUTTON_ACTIVE_TIME, timer))

    new_inventory = jnp.where(pickup, pile_item + combined, 0) + jnp.where(no_effect, inventory, 0)

    correct = inventory == plated_recipe
    wrong_value = -float(it.DELIVERY_REWARD) if config.negative_rewards else 0.0
    reward = jnp.where(deliver, jnp.where(correct, float(it.DELIVERY_REWARD), wrong_value), 0.0)
    reward = reward - jnp.where(press, float(it.BUTTON_COST), 0.0)

    # Plate pickup pays only if fewer plates are held (at step start) than pots are non-empty, and no
    # bare plate lies anywhere on the grid (the reference's anti-reward-hacking rule).
    plate_pickup = (
        pickup & (new_inventory == it.PLATE) & (counts.plates_held < counts.busy_pots) & (counts.loose_plates == 0)
    )
    shaped = shaped + jnp.where(plate_pickup, float(it.SHAPED_PLATE_PICKUP), 0.0)

    new_cell = jnp.stack([static, new_item, new_timer]).astype(jnp.int32)
    return _Interaction(new_cell, new_inventory.astype(jnp.int32), reward, shaped, deliver & correct)


def apply_interactions(config: EnvConfig, state: State, agents: Agents, actions: jax.Array):
    """Agents interact one after another, each seeing the grid as earlier agents left it."""
    grid = state.grid
    height, width = grid.shape[:2]
    num_agents = agents.x.shape[0]
    inventories = list(agents.inventory)  # a list, stacked once at the end: no scatter per agent
    # Grid-wide counts once per step, then updated by each write (one cell changes per agent): the
    # same numbers as recounting the grid before every agent, for a fraction of the work.
    counts = plate_counts(grid, agents.inventory)
    reward = jnp.zeros((), jnp.float32)
    shaped = []
    correct_delivery = jnp.zeros((), bool)
    for a in range(num_agents):
        dx, dy = it.direction_vector(agents.dir[a])
        fx = agents.x[a] + dx
        fy = agents.y[a] + dy
        on_map = (fx >= 0) & (fx < width) & (fy >= 0) & (fy < height)
        # Reference quirk (default): the facing cell is not bounds-checked; a negative index wraps
        # to the opposite edge, a too-large one reads the clamped edge cell and its write is dropped.
        wx = jnp.where(fx < 0, fx + width, fx)
        wy = jnp.where(fy < 0, fy + height, fy)
        writable = (wx < width) & (wy < height)
        rx = jnp.clip(wx, 0, width - 1)
        ry = jnp.clip(wy, 0, height - 1)
        acting = actions[a] == Action.INTERACT
        if config.fix_offmap_interaction:
            acting = acting & on_map
        cell = grid[ry, rx]
        result = interact(config, cell, inventories[a], state.recipe, counts)
        write = acting & writable
        written = jnp.where(write, result.cell, cell)
        grid = grid.at[ry, rx].set(written)
        counts = counts._replace(
            busy_pots=counts.busy_pots + _busy_pot(written).astype(jnp.int32) - _busy_pot(cell).astype(jnp.int32),
            loose_plates=counts.loose_plates
            + (written[1] == it.PLATE).astype(jnp.int32)
            - (cell[1] == it.PLATE).astype(jnp.int32),
        )
        inventories[a] = jnp.where(acting, result.inventory, inventories[a])
        reward = reward + jnp.where(acting, result.reward, 0.0)
        shaped.append(jnp.where(acting, result.shaped, 0.0))
        correct_delivery = correct_delivery | (acting & result.correct_delivery)
    agents = agents.replace(inventory=jnp.stack(inventories))
    return grid, agents, reward, jnp.stack(shaped).astype(jnp.float32), correct_delivery


def tick_timers(grid: jax.Array) -> jax.Array:
    """Pots count down and finish cooking at 0 (COOKED bit set); buttons count down to 0.

    The grid is rebuilt elementwise (a select on the channel index), so XLA fuses the tick into its
    consumers: the auto-reset select, the observation codes and the next state. Writing the two
    channels in place (``.at[:, :, 1].set``) keeps copies and an extra pass over the grid alive; a
    ``stack`` of the three channels is an element-by-element concatenate on XLA:CPU; both measured
    slower.
    """
    static, item, timer = grid[:, :, 0], grid[:, :, 1], grid[:, :, 2]
    cooking = (static == Static.POT) & (timer > 0)
    finished = cooking & (timer == 1)
    item = item | jnp.where(finished, it.COOKED, 0)
    timer = jnp.where(cooking, timer - 1, timer)
    timer = jnp.where(static == Static.BUTTON, jnp.maximum(timer - 1, 0), timer)
    channel = jnp.arange(grid.shape[-1], dtype=jnp.int32)
    return jnp.where(channel == 1, item[:, :, None], jnp.where(channel == 2, timer[:, :, None], grid))


def transition(config: EnvConfig, key: jax.Array, state: State, actions: jax.Array) -> Transition:
    """One step without observations or auto-reset (the reference's ``step_env`` minus ``get_obs``)."""
    actions = jnp.asarray(actions, dtype=jnp.int32)
    agents = move_agents(state, actions)
    grid, agents, reward, shaped, correct = apply_interactions(config, state, agents, actions)
    grid = tick_timers(grid)
    recipe = state.recipe
    if config.sample_recipe_on_delivery:
        _, recipe_key = jax.random.split(key)
        recipe = jnp.where(correct, sample_recipe(config, recipe_key), recipe)
    step = state.step + 1
    done = (step >= config.max_steps) | state.done
    new_state = state.replace(
        agents=agents, grid=grid, recipe=recipe, step=step, done=done, new_correct_delivery=correct
    )
    return Transition(new_state, reward, shaped, correct)
