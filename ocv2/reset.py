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


def validate_buffer(config: EnvConfig, buffer: State, what: str = "initial_state_buffer") -> None:
    """Check a reset buffer (states with a leading batch axis) against the layout; raise naming the field.

    Shapes and dtypes are checked always (they are static, so this is free under ``jit``); the contents
    (kitchen, agent cells and directions, recipe) only where the arrays are concrete, not traced.
    """
    if not isinstance(buffer, State):
        raise TypeError(f"{what} must be an ocv2.State with a leading batch axis, got {type(buffer).__name__}")
    size = np.shape(buffer.step)[0] if np.ndim(buffer.step) == 1 else None
    if size is None or size < 1:
        raise ValueError(
            f"{what} must have a leading batch axis of at least 1 state; step has shape {np.shape(buffer.step)}"
        )
    _check_fields(config, buffer, what, (size,), f" ({size} states)")
    _check_contents(config, buffer, lambda i: f"{what} state {i}")


def validate_state(config: EnvConfig, state: State, what: str = "state", contents: bool = True) -> None:
    """Check one state against the layout: shapes and dtypes always; with ``contents``, when concrete, what
    ``validate_buffer`` checks too. Raise naming the field."""
    if not isinstance(state, State):
        raise TypeError(f"{what} must be an ocv2.State, got {type(state).__name__}")
    _check_fields(config, state, what, (), "")
    if contents:
        batched = jax.tree.map(lambda leaf: leaf if _is_traced(leaf) else np.asarray(leaf)[None], state)
        _check_contents(config, batched, lambda _: what)


def _state_fields(state: State) -> dict:
    return {
        "agents.x": state.agents.x,
        "agents.y": state.agents.y,
        "agents.dir": state.agents.dir,
        "agents.inventory": state.agents.inventory,
        "grid": state.grid,
        "recipe": state.recipe,
        "step": state.step,
        "done": state.done,
        "new_correct_delivery": state.new_correct_delivery,
        "ingredient_permutations": state.ingredient_permutations,
    }


def _expected_fields(config: EnvConfig) -> dict:
    """Per-state shape and dtype of every field (the dtypes ``State`` is built with)."""
    n_agents, n_ing = config.num_agents, config.num_ingredients
    height, width = config.layout.height, config.layout.width
    int32, boolean = np.dtype(np.int32), np.dtype(bool)
    return {
        "agents.x": ((n_agents,), int32),
        "agents.y": ((n_agents,), int32),
        "agents.dir": ((n_agents,), int32),
        "agents.inventory": ((n_agents,), int32),
        "grid": ((height, width, 3), int32),
        "recipe": ((), int32),
        "step": ((), int32),
        "done": ((), boolean),
        "new_correct_delivery": ((), boolean),
        "ingredient_permutations": ((n_agents, n_ing), int32),
    }


def _dtype(leaf) -> np.dtype:
    """The dtype JAX computes with (a numpy int64 or a Python int enters as int32 unless x64 is on)."""
    raw = leaf.dtype if hasattr(leaf, "dtype") else np.asarray(leaf).dtype
    return np.dtype(jax.dtypes.canonicalize_dtype(raw))


def _check_fields(config: EnvConfig, state: State, what: str, batch: tuple, count: str) -> None:
    actual = _state_fields(state)
    for name, (shape, dtype) in _expected_fields(config).items():
        got = tuple(np.shape(actual[name]))
        if got != batch + shape:
            raise ValueError(
                f"{what}.{name} has shape {got}, expected {batch + shape} for layout {config.layout.name!r}{count}"
            )
        if _dtype(actual[name]) != dtype:
            raise ValueError(
                f"{what}.{name} has dtype {_dtype(actual[name])}, expected {dtype} (as ocv2.State is built); "
                f"cast it with .astype(jnp.{dtype.name})"
            )


def _is_traced(leaf) -> bool:
    return isinstance(leaf, jax.core.Tracer)


def _check_contents(config: EnvConfig, batch: State, where) -> None:
    """Value checks of a batch of states, each on the fields that are concrete; ``where(i)`` names state i."""
    layout = config.layout
    static = np.asarray(layout.static_objects)
    if not _is_traced(batch.grid):
        _check_kitchen(np.asarray(batch.grid)[..., 0], layout, where)
    if not (_is_traced(batch.agents.x) or _is_traced(batch.agents.y)):
        _check_agent_cells(np.asarray(batch.agents.x), np.asarray(batch.agents.y), static, where)
    if not _is_traced(batch.agents.dir):
        _check_directions(np.asarray(batch.agents.dir), where)
    if not _is_traced(batch.recipe):
        _check_recipes(np.asarray(batch.recipe), layout, where)


def _check_kitchen(grid_static: np.ndarray, layout, where) -> None:
    difference = layout.first_difference(grid_static)
    if difference is not None:
        index, row, column = difference
        raise ValueError(
            f"{where(index)} has a different kitchen than layout {layout.name!r} (grid static cell at row {row}, "
            f"column {column} is {grid_static[index, row, column]}, the layout's is {layout.static_objects[row, column]})"
        )


def _check_agent_cells(xs: np.ndarray, ys: np.ndarray, static: np.ndarray, where) -> None:
    """Every agent on a floor cell of the map, no two on one cell."""
    height, width = static.shape
    inside = (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
    if not inside.all():
        index, agent = (int(v) for v in np.argwhere(~inside)[0])
        raise ValueError(
            f"{where(index)}: agents.x/agents.y put agent {agent} at (x={xs[index, agent]}, y={ys[index, agent]}), "
            f"outside the {height}x{width} map"
        )
    on_floor = static[ys, xs] == Static.FLOOR
    if not on_floor.all():
        index, agent = (int(v) for v in np.argwhere(~on_floor)[0])
        raise ValueError(
            f"{where(index)}: agents.x/agents.y put agent {agent} on a non-floor cell "
            f"(row {ys[index, agent]}, column {xs[index, agent]})"
        )
    cells = ys * width + xs
    for a in range(cells.shape[1]):
        for b in range(a + 1, cells.shape[1]):
            shared = np.flatnonzero(cells[:, a] == cells[:, b])
            if len(shared):
                index = int(shared[0])
                raise ValueError(
                    f"{where(index)}: agents.x/agents.y put agents {a} and {b} on the same cell "
                    f"(row {ys[index, a]}, column {xs[index, a]})"
                )


def _check_directions(directions: np.ndarray, where) -> None:
    bad = (directions < 0) | (directions >= len(it.Direction))
    if bad.any():
        index, agent = (int(v) for v in np.argwhere(bad)[0])
        raise ValueError(
            f"{where(index)}: agents.dir[{agent}] is {directions[index, agent]}, expected 0..3 (UP, DOWN, RIGHT, LEFT)"
        )


def _check_recipes(recipes: np.ndarray, layout, where) -> None:
    possible = {it.recipe_encoding_np(r): list(r) for r in layout.possible_recipes}
    bad = ~np.isin(recipes, list(possible))
    if bad.any():
        index = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{where(index)}: recipe is {recipes[index]}, not the encoding of a possible recipe of layout "
            f"{layout.name!r} ({', '.join(f'{code} = {r}' for code, r in possible.items())})"
        )
