"""Initial states: the layout's start, random starts, other-play permutations, buffer resets.

The order and arguments of every ``jax.random`` call follow the reference (JaxMARL 0.2.0), so the
same key gives the same state -- including its key-reuse quirk (the other-play permutations and the
randomisation are drawn from the same sub-key).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.config import EnvConfig
from ocv2.dynamics import sample_recipe
from ocv2.items import Static
from ocv2.state import Agents, State

_INVENTORY_P = (0.5, 0.1, 0.25, 0.15)  # empty, plate, ingredient, dish
_POT_P = (0.4, 0.35, 0.15, 0.1)  # untouched, partly filled, cooking, cooked
_COUNTER_P = (0.5, 0.1, 0.3, 0.1)  # empty, plate, ingredient, dish


def layout_state(config: EnvConfig, recipe: jax.Array, permutations: jax.Array) -> State:
    """The layout's own start: agents at their marks facing up, empty hands, empty counters and pots."""
    layout = config.layout
    static = jnp.asarray(layout.static_objects, dtype=jnp.int32)
    zeros = jnp.zeros_like(static)
    xs, ys = zip(*layout.agent_positions)
    num_agents = layout.num_agents
    agents = Agents(
        x=jnp.asarray(xs, dtype=jnp.int32),
        y=jnp.asarray(ys, dtype=jnp.int32),
        dir=jnp.full((num_agents,), int(it.Direction.UP), dtype=jnp.int32),  # int(): an IntEnum fill is weak-typed
        inventory=jnp.zeros((num_agents,), dtype=jnp.int32),
    )
    return State(
        agents=agents,
        grid=jnp.stack([static, zeros, zeros], axis=-1),
        recipe=recipe,
        step=jnp.zeros((), jnp.int32),
        done=jnp.zeros((), bool),
        new_correct_delivery=jnp.zeros((), bool),
        ingredient_permutations=permutations,
    )


def identity_permutations(config: EnvConfig) -> jax.Array:
    n, num_agents = config.num_ingredients, config.num_agents
    return jnp.tile(jnp.arange(n, dtype=jnp.int32), (num_agents, 1))


def sample_permutations(config: EnvConfig, key: jax.Array) -> jax.Array:
    """Per-agent ingredient permutations for other-play (identity when OP is off).

    Row a maps observation slot j to true ingredient ``m[a, j]``; only the configured ingredients move.
    """
    if not config.op_enabled:
        return identity_permutations(config)
    chosen = jnp.asarray(config.op_ingredient_permutations, dtype=jnp.int32)
    _, sub = jax.random.split(key)
    agent_keys = jax.random.split(sub, config.num_agents)
    rows = []
    for a in range(config.num_agents):
        shuffled = jax.random.permutation(agent_keys[a], chosen)
        rows.append(jnp.arange(config.num_ingredients, dtype=jnp.int32).at[chosen].set(shuffled))
    return jnp.stack(rows)


def randomize_positions(config: EnvConfig, state: State, key: jax.Array) -> State:
    """Each agent to a random free cell of its own room, then random directions."""
    layout = config.layout
    rooms = jnp.asarray(layout.room_labels)
    height, width = rooms.shape
    agents = state.agents
    num_agents = layout.num_agents
    key, sub = jax.random.split(key)
    agent_keys = jax.random.split(sub, num_agents)
    taken = jnp.zeros((height, width), dtype=bool)
    xs, ys = [], []
    for a in range(num_agents):
        allowed = (rooms == rooms[agents.y[a], agents.x[a]]) & ~taken
        allowed = allowed.reshape(-1)
        p = allowed / jnp.sum(allowed)
        flat = jax.random.choice(agent_keys[a], allowed.size, (), p=p)
        x, y = flat % width, flat // width
        taken = taken.at[y, x].set(True)
        xs.append(x)
        ys.append(y)
    _, sub = jax.random.split(key)
    directions = jax.random.randint(sub, (num_agents,), 0, len(it.Direction))
    new_agents = agents.replace(
        x=jnp.stack(xs).astype(jnp.int32), y=jnp.stack(ys).astype(jnp.int32), dir=directions.astype(jnp.int32)
    )
    return state.replace(agents=new_agents)


def _random_item(config: EnvConfig, k_pick, k_ing, k_dish, probabilities) -> jax.Array:
    """One of [nothing, a plate, a random raw ingredient, a random finished dish] (inventories, counters)."""
    ingredient = it.ingredient_unit(jax.random.randint(k_ing, (), 0, config.num_ingredients))
    dish = sample_recipe(config, k_dish) | it.PLATE | it.COOKED
    options = jnp.stack([jnp.int32(it.EMPTY), jnp.int32(it.PLATE), ingredient, dish]).astype(jnp.int32)
    return options[jax.random.choice(k_pick, 4, (), p=jnp.array(probabilities))]


def _random_inventory(config: EnvConfig, key: jax.Array) -> jax.Array:
    k_dish, k_ing, k_pick = jax.random.split(key, 3)  # the reference's key order differs per use
    return _random_item(config, k_pick, k_ing, k_dish, _INVENTORY_P)


def _random_pot(config: EnvConfig, cell: jax.Array, key: jax.Array) -> jax.Array:
    k_pick, k_ing, k_num, k_timer = jax.random.split(key, 4)
    units = it.ingredient_unit(jax.random.randint(k_ing, (3,), 0, config.num_ingredients))
    count = jax.random.randint(k_num, (), 1, 4)
    partial = jnp.sum(jnp.where(jnp.arange(3) < count, units, 0))
    full = partial if config.start_cooking_interaction else jnp.sum(units)
    timer = jax.random.randint(k_timer, (), 0, it.POT_COOK_TIME) + 1
    static = cell[0]
    options = jnp.stack(
        [
            cell,
            jnp.stack([static, partial, jnp.int32(0)]),
            jnp.stack([static, full, timer]),
            jnp.stack([static, full | it.COOKED, jnp.int32(0)]),
        ]
    ).astype(jnp.int32)
    return options[jax.random.choice(k_pick, 4, (), p=jnp.array(_POT_P))]


def _random_counter(config: EnvConfig, cell: jax.Array, key: jax.Array) -> jax.Array:
    k_pick, k_ing, k_dish = jax.random.split(key, 3)
    return cell.at[1].set(_random_item(config, k_pick, k_ing, k_dish, _COUNTER_P))


def randomize_state(config: EnvConfig, state: State, key: jax.Array) -> State:
    """``random_reset``: random positions, inventories, pot contents/timers and counter items."""
    key, sub = jax.random.split(key)
    state = randomize_positions(config, state, sub)
    key, sub = jax.random.split(key)
    inventories = jax.vmap(lambda k: _random_inventory(config, k))(jax.random.split(sub, config.num_agents))
    key, sub = jax.random.split(key)
    height, width = state.grid.shape[:2]
    cell_keys = jax.random.split(sub, (height, width))

    def cell_fn(cell, cell_key):
        return jnp.where(
            cell[0] == Static.POT,
            _random_pot(config, cell, cell_key),
            jnp.where(cell[0] == Static.WALL, _random_counter(config, cell, cell_key), cell),
        )

    grid = jax.vmap(jax.vmap(cell_fn))(state.grid, cell_keys)
    return state.replace(agents=state.agents.replace(inventory=inventories), grid=grid)


def default_reset_state(config: EnvConfig, key: jax.Array) -> State:
    """The reference's ``reset`` without a buffer, observation excluded."""
    key, k_recipe = jax.random.split(key)
    recipe = sample_recipe(config, k_recipe)
    permutations = sample_permutations(config, key)
    state = layout_state(config, recipe, permutations)
    _, k_random = jax.random.split(key)  # the same sub-key the permutations used (reference quirk)
    if config.random_reset:
        state = randomize_state(config, state, k_random)
    elif config.random_agent_positions:
        state = randomize_positions(config, state, k_random)
    return state


def state_from(config: EnvConfig, key: jax.Array, state: State) -> State:
    """Start an episode from a given state: keep kitchen, agents and recipe; clear the episode fields."""
    return state.replace(
        step=jnp.zeros((), jnp.int32),
        done=jnp.zeros((), bool),
        new_correct_delivery=jnp.zeros((), bool),
        ingredient_permutations=sample_permutations(config, key),
    )


def buffer_reset_state(config: EnvConfig, key: jax.Array, buffer: State) -> State:
    """Draw a buffer state uniformly (with the reset key itself, as the reference does) and start from it."""
    size = buffer.step.shape[0]
    index = jax.random.randint(key, (), 0, size)
    chosen = jax.tree.map(lambda leaf: leaf[index], buffer)
    return state_from(config, key, chosen)


def validate_buffer(config: EnvConfig, buffer: State) -> None:
    """Shape-check a reset buffer against the layout; raise ValueError naming the bad field."""
    if not isinstance(buffer, State):
        raise TypeError(
            f"initial_state_buffer must be an ocv2.State with a leading batch axis, got {type(buffer).__name__}"
        )
    n_agents, n_ing = config.num_agents, config.num_ingredients
    height, width = config.layout.height, config.layout.width
    size = np.shape(buffer.step)[0] if np.ndim(buffer.step) == 1 else None
    if size is None or size < 1:
        raise ValueError(
            f"initial_state_buffer must have a leading batch axis of at least 1 state; step has shape {np.shape(buffer.step)}"
        )
    expected = {
        "agents.x": (size, n_agents),
        "agents.y": (size, n_agents),
        "agents.dir": (size, n_agents),
        "agents.inventory": (size, n_agents),
        "grid": (size, height, width, 3),
        "recipe": (size,),
        "step": (size,),
        "done": (size,),
        "new_correct_delivery": (size,),
        "ingredient_permutations": (size, n_agents, n_ing),
    }
    actual = {
        "agents.x": buffer.agents.x,
        "agents.y": buffer.agents.y,
        "agents.dir": buffer.agents.dir,
        "agents.inventory": buffer.agents.inventory,
        "grid": buffer.grid,
        "recipe": buffer.recipe,
        "step": buffer.step,
        "done": buffer.done,
        "new_correct_delivery": buffer.new_correct_delivery,
        "ingredient_permutations": buffer.ingredient_permutations,
    }
    for name, shape in expected.items():
        if tuple(np.shape(actual[name])) != shape:
            raise ValueError(
                f"initial_state_buffer.{name} has shape {tuple(np.shape(actual[name]))}, expected {shape} "
                f"for layout {config.layout.name!r} ({size} states)"
            )
    if not isinstance(buffer.grid, jax.core.Tracer):
        static = np.asarray(buffer.grid)[..., 0]
        if not (static == np.asarray(config.layout.static_objects)[None]).all():
            bad = np.argwhere(static != np.asarray(config.layout.static_objects)[None])[0]
            raise ValueError(
                f"initial_state_buffer state {bad[0]} has a different kitchen than layout {config.layout.name!r} "
                f"(static cell at row {bad[1]}, column {bad[2]})"
            )
