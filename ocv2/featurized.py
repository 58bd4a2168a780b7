"""Featurized observation: an Overcooked-AI style feature vector per agent.

Matches the reference's ``observation_type="featurized"`` value for value (float32). Only
single-ingredient layouts are supported (the feature set is Overcooked-AI's onion/tomato one).

Per-player block (46 values, ``PLAYER_FEATURES``), for player p:

====== ==================================================================================
0-3    facing one-hot (UP, DOWN, RIGHT, LEFT)
4-7    held item one-hot: [raw ingredient 0, finished soup, plate, raw ingredient 1]
8-9    (dx, dy) to the closest source of ingredient 0 (pile, or a loose ingredient not in a pot)
10-11  same for ingredient 1 (always (0, 0) on single-ingredient layouts)
12-13  closest plate source (plate pile or loose plate)
14-15  closest finished soup lying outside a pot
16-17  [3 if a finished soup lies anywhere on the grid or p holds one else 0, 0]
18-19  closest goal
20-21  closest empty counter
22-31  closest pot: [1, empty, 3 ingredients, cooking, cooked, #ingredients, 0, timer, dx, dy]
32-41  second-closest pot, same layout (a pot block is all zeros when there is no such pot)
42-45  "cell is not floor" for the neighbour UP, DOWN, RIGHT, LEFT
====== ==================================================================================

"Closest" is measured in actions: the fewest moves/turns for p, starting from its cell and facing,
to stand next to the target and face it. Other agents are ignored; a direction key turns the agent in
place only if the cell ahead is not floor (otherwise it moves). Ties go to the lowest row-major cell
index. (dx, dy) = target - p, and (0, 0) when no target is reachable or p holds the item in question.

Agent i's vector (``48 * N`` values) = [block_i, block_j for each j != i in index order,
(x_j - x_i, y_j - y_i) for each j != i, (x_i, y_i)].

All layout-dependent work (shortest action counts from every (cell, facing) to every target cell)
is done once with numpy in ``make_featurizer``; a call is then a handful of table look-ups and
argmins, usable under ``jit`` and ``vmap``.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.items import Direction, Static

NUM_POTS = 2
POT_FEATURES = 10
PLAYER_FEATURES = 4 + 4 + 6 * 2 + 2 + NUM_POTS * POT_FEATURES + 4  # 46

# Finished Overcooked-AI soup: three of ingredient 0, plated and cooked.
SOUP = 3 * it.ingredient_unit(0) | it.PLATE | it.COOKED

# Cost of a target that cannot be reached (or is no target); any finite cost is far below it.
_UNREACHABLE = np.iinfo(np.int32).max

# The direction pointing the other way, indexed by Direction.
_OPPOSITE = np.array([Direction.DOWN, Direction.UP, Direction.LEFT, Direction.RIGHT])


def _action_distances(floor: np.ndarray) -> np.ndarray:
    """Fewest actions from each (floor cell, facing) to each (cell, facing): int64[P, 4, H, W, 4].

    Floor cells are numbered in row-major order (P of them). A move in direction d from cell c goes
    to c + d when that cell is floor and then faces d; otherwise the agent turns to face d in place.
    Every such action costs 1. All P*4 starts are relaxed together (unit costs, so the number of
    sweeps is the longest shortest path).
    """
    height, width = floor.shape
    fy, fx = np.nonzero(floor)
    num_floor = fy.size
    inf = np.iinfo(np.int64).max // 4
    dist = np.full((num_floor, 4, height, width, 4), inf, dtype=np.int64)
    starts = np.arange(num_floor)
    for d in range(4):
        dist[starts, d, fy, fx, d] = 0

    # blocked[y, x, d]: the cell ahead of (y, x) in direction d is outside the map or not floor.
    padded = np.zeros((height + 2, width + 2), dtype=bool)
    padded[1:-1, 1:-1] = floor
    blocked = np.zeros((height, width, 4), dtype=bool)
    for d, (dx, dy) in enumerate(it.DIRECTION_VECTORS):
        blocked[:, :, d] = ~padded[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width]
    blocked &= floor[..., None]

    while True:
        best = dist.min(axis=-1)  # [..., H, W]: cheapest way to be on the cell, any facing
        step = np.full_like(dist, inf)
        for d, (dx, dy) in enumerate(it.DIRECTION_VECTORS):
            # Arrive at (y, x) facing d by moving from (y - dy, x - dx).
            ys = slice(max(dy, 0), height + min(dy, 0))
            xs = slice(max(dx, 0), width + min(dx, 0))
            src_ys = slice(max(-dy, 0), height + min(-dy, 0))
            src_xs = slice(max(-dx, 0), width + min(-dx, 0))
            step[..., ys, xs, d] = best[..., src_ys, src_xs]
            # Or turn to d on the spot when d is blocked.
            step[..., d] = np.where(blocked[:, :, d], np.minimum(step[..., d], best), step[..., d])
        step = np.where(floor[..., None], step + 1, inf)
        relaxed = np.minimum(dist, step)
        if np.array_equal(relaxed, dist):
            return dist
        dist = relaxed


def _target_costs(floor: np.ndarray) -> np.ndarray:
    """Actions from each (floor cell, facing) until facing each cell from a neighbour: int64[P, 4, H*W].

    Only non-floor cells can be targets (one cannot face a floor cell without stepping onto it, and
    the reference never counts floor targets); the rest stay ``_UNREACHABLE``.
    """
    height, width = floor.shape
    dist = _action_distances(floor)
    inf = np.iinfo(np.int64).max // 4
    cost = np.full(dist.shape[:2] + (height, width), inf, dtype=np.int64)
    for d, (dx, dy) in enumerate(it.DIRECTION_VECTORS):
        # Target (y, x) is faced from its neighbour (y + dy, x + dx) looking the opposite way.
        ys = slice(max(-dy, 0), height + min(-dy, 0))
        xs = slice(max(-dx, 0), width + min(-dx, 0))
        nbr_ys = slice(max(dy, 0), height + min(dy, 0))
        nbr_xs = slice(max(dx, 0), width + min(dx, 0))
        cost[..., ys, xs] = np.minimum(cost[..., ys, xs], dist[..., nbr_ys, nbr_xs, _OPPOSITE[d]])
    cost = np.where(floor | (cost >= inf), _UNREACHABLE, cost)
    return cost.reshape(cost.shape[:2] + (height * width,))


def _neighbour_cells(height: int, width: int) -> np.ndarray:
    """Flat index of the cell read as neighbour UP, DOWN, RIGHT, LEFT of each cell: int32[H*W, 4].

    Reproduces the reference's jnp indexing at the map edge (index -1 wraps to the last row/column,
    index H or W is clamped to the last one). Built-in layouts never put floor on the edge, so this
    only matters for custom maps.
    """
    ys, xs = np.divmod(np.arange(height * width), width)
    out = np.empty((height * width, 4), dtype=np.int32)
    for d, (dx, dy) in enumerate(it.DIRECTION_VECTORS):
        ny, nx = ys + dy, xs + dx
        ny = np.where(ny < 0, ny + height, np.minimum(ny, height - 1))
        nx = np.where(nx < 0, nx + width, np.minimum(nx, width - 1))
        out[:, d] = ny * width + nx
    return out


@dataclass(frozen=True, eq=False)
class Featurizer:
    """``f(state) -> float32[N, f.size]``; build with ``make_featurizer``."""

    num_agents: int
    height: int
    width: int
    size: int
    _row_of_cell: np.ndarray  # int32[H*W]: row of _costs for an agent on this cell (last row = off floor)
    _costs: np.ndarray  # int32[P + 1, 4, H*W]
    _on_floor: np.ndarray  # bool[H*W]
    _neighbours: np.ndarray  # int32[H*W, 4]
    _others: np.ndarray  # int32[N, N - 1]: for each agent, the other agents in index order

    def __call__(self, state) -> jax.Array:
        grid = state.grid.reshape(self.height * self.width, 3)
        static, item, timer = grid[:, 0], grid[:, 1], grid[:, 2]
        agents = state.agents
        blocks = jax.vmap(self._player_block, in_axes=(None, None, None, 0, 0, 0, 0))(
            static, item, timer, agents.x, agents.y, agents.dir, agents.inventory
        )
        pos = jnp.stack([agents.x, agents.y], axis=-1)
        others = jnp.asarray(self._others)
        n = self.num_agents
        # Explicit sizes: with one agent these are empty and -1 could not be inferred.
        other_blocks = blocks[others].reshape(n, (n - 1) * PLAYER_FEATURES)
        offsets = (pos[others] - pos[:, None, :]).reshape(n, (n - 1) * 2)
        return jnp.concatenate([blocks, other_blocks, offsets.astype(jnp.float32), pos.astype(jnp.float32)], axis=-1)

    def _player_block(self, static, item, timer, x, y, facing, held):
        cell = y * self.width + x
        costs = jnp.asarray(self._costs)[jnp.asarray(self._row_of_cell)[cell], facing]
        # The reference answers "here" without a search when the agent's own cell is a target, but
        # only if that cell is floor (off-floor agents find nothing at all).
        on_floor = jnp.asarray(self._on_floor)[cell]

        def closest(targets):
            """(flat index, found) of the cheapest target; lowest index on ties."""
            here = targets[cell] & on_floor
            masked = jnp.where(targets, costs, _UNREACHABLE)
            best = jnp.argmin(masked)
            found = masked[best] < _UNREACHABLE
            return jnp.where(here, cell, best), here | found

        def offset(index, found):
            ty, tx = jnp.divmod(index, self.width)
            return jnp.where(found, jnp.stack([tx - x, ty - y]), 0)

        not_in_pot = static != Static.POT

        def source(pile, thing):
            """Closest pile of ``thing`` or loose ``thing``; (0, 0) while the player holds it.

            Holding it makes the player's own cell the (only relevant) target: the reference puts
            ``held == thing`` on the own cell, so a hit there reports distance zero.
            """
            targets = (static == pile) | ((item == thing) & not_in_pot)
            targets = targets.at[cell].set(held == thing)
            return offset(*closest(targets))

        ingredient_0 = source(Static.INGREDIENT_PILE, it.ingredient_unit(0))
        ingredient_1 = source(Static.INGREDIENT_PILE + 1, it.ingredient_unit(1))
        plate = source(Static.PLATE_PILE, it.PLATE)
        # No pile makes soups; -1 never matches a static id.
        soup = source(-1, SOUP)
        soup_exists = jnp.any(item == SOUP) | (held == SOUP)
        soup_count = jnp.stack([jnp.where(soup_exists, 3, 0), 0])
        goal = offset(*closest(static == Static.GOAL))
        counter = offset(*closest((static == Static.WALL) & (item == it.EMPTY)))

        pots = static == Static.POT
        pot_blocks = []
        for _ in range(NUM_POTS):
            index, found = closest(pots)
            contents, left = item[index], timer[index]
            count = it.ingredient_count(contents)
            block = jnp.stack(
                [
                    jnp.int32(1),
                    (contents == it.EMPTY).astype(jnp.int32),
                    (count == 3).astype(jnp.int32),
                    (left > 0).astype(jnp.int32),
                    ((contents & it.COOKED) == it.COOKED).astype(jnp.int32),
                    count,
                    jnp.int32(0),
                    left,
                    *offset(index, True),
                ]
            )
            pot_blocks.append(jnp.where(found, block, 0))
            # The next pass looks for the next pot. (When none was found the index is 0 and
            # nothing reachable is left anyway.)
            pots = pots.at[index].set(False)

        not_floor = static[jnp.asarray(self._neighbours)[cell]] != Static.FLOOR

        return jnp.concatenate(
            [
                jax.nn.one_hot(facing, 4, dtype=jnp.float32),
                (held == jnp.array([it.ingredient_unit(0), SOUP, it.PLATE, it.ingredient_unit(1)])).astype(jnp.float32),
                *(v.astype(jnp.float32) for v in (ingredient_0, ingredient_1, plate, soup, soup_count, goal, counter)),
                *(b.astype(jnp.float32) for b in pot_blocks),
                not_floor.astype(jnp.float32),
            ]
        )


def make_featurizer(layout) -> Featurizer:
    """Build the featurized-observation function for ``layout`` (single-ingredient layouts only)."""
    if layout.num_ingredients != 1:
        raise ValueError(
            f"the featurized observation supports only single-ingredient layouts; this layout has "
            f"{layout.num_ingredients} ingredients"
        )
    static = np.asarray(layout.static_objects)
    height, width = static.shape
    floor = static == Static.FLOOR
    costs = _target_costs(floor)
    num_floor = costs.shape[0]
    # Agents off the floor (only in hand-made states) get a row with no reachable target.
    costs = np.concatenate([costs, np.full((1, 4, height * width), _UNREACHABLE, np.int64)])
    row_of_cell = np.full(height * width, num_floor, dtype=np.int32)
    row_of_cell[np.flatnonzero(floor)] = np.arange(num_floor, dtype=np.int32)
    # Targets are judged per agent from where it stands: every non-floor cell next to a floor cell of
    # its room has a finite cost, every other cell is _UNREACHABLE. That is exactly the reference's
    # "own room grown by one cell" restriction, so no separate room mask is needed.
    n = len(layout.agent_positions)
    others = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int32).reshape(n, n - 1)
    return Featurizer(
        num_agents=n,
        height=height,
        width=width,
        size=PLAYER_FEATURES * n + 2 * (n - 1) + 2,
        _row_of_cell=row_of_cell,
        _costs=costs.astype(np.int32),
        _on_floor=floor.reshape(-1),
        _neighbours=_neighbour_cells(height, width),
        _others=others,
    )
