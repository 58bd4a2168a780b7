"""Encodings shared by every rule of the game: static cell ids, item bits, directions, actions.

The numbers are the reference's (JaxMARL 0.2.0 ``overcooked_v2``) so that states, observations and
archived trajectories are interchangeable with it. See ``docs/environment.md`` for the full tables.
"""

from __future__ import annotations

import enum

import jax.numpy as jnp
import numpy as np

# --- game constants (module-level in the reference too; the paper calls some "configurable") ---
DELIVERY_REWARD = 20
POT_COOK_TIME = 20
BUTTON_ACTIVE_TIME = 10
BUTTON_COST = 5
MAX_INGREDIENTS_IN_POT = 3

SHAPED_PLACEMENT_IN_POT = 3
SHAPED_POT_START_COOKING = 5
SHAPED_DISH_PICKUP = 5
SHAPED_PLATE_PICKUP = 3

# An int32 item has room for 15 two-bit ingredient counters above the two flag bits.
MAX_INGREDIENT_KINDS = 10  # layout characters '0'..'9'
_COUNT_FIELDS = 15


class Static(enum.IntEnum):
    """Layer 0 of the grid: what is built into a cell."""

    FLOOR = 0
    WALL = 1  # a counter: items can be put on it
    AGENT = 2  # renderer only, never in a state
    SELF_AGENT = 3  # unused by the reference, kept so ids line up
    GOAL = 4
    POT = 5
    RECIPE_INDICATOR = 6
    BUTTON = 7  # button recipe indicator
    PLATE_PILE = 9
    INGREDIENT_PILE = 10  # + ingredient index


class Direction(enum.IntEnum):
    UP = 0
    DOWN = 1
    RIGHT = 2
    LEFT = 3


class Action(enum.IntEnum):
    RIGHT = 0
    DOWN = 1
    LEFT = 2
    UP = 3
    STAY = 4
    INTERACT = 5


NUM_ACTIONS = len(Action)

# (dx, dy) per Direction, row order = Direction ids.
DIRECTION_VECTORS = np.array([(0, -1), (0, 1), (1, 0), (-1, 0)], dtype=np.int32)
# Direction per Action; -1 for actions that do not move.
ACTION_DIRECTION = np.array([Direction.RIGHT, Direction.DOWN, Direction.LEFT, Direction.UP, -1, -1], dtype=np.int32)


def _select_table(index, table):
    """``table[index]`` for a small constant table, as a chain of selects.

    Under ``vmap`` a lookup in a constant array becomes a gather (its own XLA kernel, plus index
    building); a few compares fuse into the surrounding elementwise code instead.
    """
    out = jnp.full(jnp.shape(index), int(table[-1]), jnp.int32)
    for i in range(len(table) - 2, -1, -1):
        out = jnp.where(index == i, int(table[i]), out)
    return out


def action_direction(action):
    """``ACTION_DIRECTION[action]`` (the Direction an action moves in, -1 if none) for action in 0..5."""
    return _select_table(action, ACTION_DIRECTION)


def direction_vector(direction):
    """``DIRECTION_VECTORS[direction]`` as (dx, dy) for direction in 0..3."""
    return _select_table(direction, DIRECTION_VECTORS[:, 0]), _select_table(direction, DIRECTION_VECTORS[:, 1])


# --- item encoding (layer 1 of the grid, inventories, recipes) ---
EMPTY = 0
PLATE = 1 << 0
COOKED = 1 << 1


def ingredient_unit(index):
    """Encoding of one raw ingredient ``index`` (works on ints and arrays)."""
    return 4 << (2 * index)


def recipe_encoding(ingredients) -> jnp.ndarray:
    """Sum of the units of the recipe's ingredients (no flag bits), for a (..., 3) index array."""
    ingredients = jnp.asarray(ingredients)
    return jnp.sum(ingredient_unit(ingredients), axis=-1).astype(jnp.int32)


def recipe_encoding_np(recipe) -> int:
    return int(sum(4 << (2 * int(i)) for i in recipe))


def ingredient_count(item):
    """Total number of ingredients in an item, flags ignored."""
    rest = item >> 2
    total = jnp.zeros_like(item)
    for field in range(_COUNT_FIELDS):
        total = total + ((rest >> (2 * field)) & 3)
    return total


def is_raw_ingredient(item):
    """The reference's test for "can be put into a pot": some ingredient bit set, not plated."""
    return ((item >> 2) != 0) & ((item & PLATE) == 0)


def item_channels(item, num_ingredients: int):
    """Split items into observation channels [PLATE bit, COOKED bit, count_0 .. count_{n-1}].

    ``item`` has any shape; the result has one more trailing axis of size ``2 + n``.
    """
    shifts = jnp.array([0, 1] + [2 * (i + 1) for i in range(num_ingredients)], dtype=jnp.int32)
    masks = jnp.array([1, 1] + [3] * num_ingredients, dtype=jnp.int32)
    return (item[..., None] >> shifts) & masks


def item_ingredient_counts_np(item: int, num_ingredients: int) -> list[int]:
    return [(int(item) >> (2 + 2 * i)) & 3 for i in range(num_ingredients)]
