"""Grid observations, as the reference builds them: per-agent (H, W, C) channel stacks, optional view window.

Channel order (n ingredients, item block = [plate bit, cooked bit, count_0 .. count_{n-1}]):
ego position, ego direction (4), ego inventory block, other agents' position / directions / inventory
blocks (summed), static one-hots (counter, goal, pot, recipe indicator, button, plate pile),
ingredient piles (n), grid item block, recipe block (at indicators and active buttons), pot timer,
and, with ``indicate_successful_delivery``, the delivery flag at goals. C = 25 + 5n (+1).

Values equal the reference's; the dtype is uint8 by default (the reference uses int32).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.config import EnvConfig
from ocv2.items import Static
from ocv2.state import State

_STATIC_CHANNELS = (Static.WALL, Static.GOAL, Static.POT, Static.RECIPE_INDICATOR, Static.BUTTON, Static.PLATE_PILE)


def full_channels(config: EnvConfig) -> int:
    """C = 25 + 5n, +1 with the delivery indicator (the reference's full observation)."""
    return 25 + 5 * config.num_ingredients + int(config.indicate_successful_delivery)


def num_channels(config: EnvConfig) -> int:
    """Channels of the default observation, after the optional paper truncation."""
    n = config.num_ingredients
    full = full_channels(config)
    if config.paper_obs_truncation and config.view_radius is not None:
        # The paper's environment version declared 18 + 4(n + 2) (+1) channels and its view window
        # sliced to that, silently dropping the last ones for n >= 2.
        return min(full, 18 + 4 * (n + 2) + int(config.indicate_successful_delivery))
    return full


def grid_obs_shape(config: EnvConfig) -> tuple[int, int, int]:
    radius = config.view_radius
    if radius is None:
        return (config.layout.height, config.layout.width, num_channels(config))
    side = 2 * radius + 1
    return (side, side, num_channels(config))


def _permute_item(code: jax.Array, perm: jax.Array, n: int) -> jax.Array:
    """An item or recipe code as an observer with ingredient mapping ``perm`` sees it (other-play).

    Slot j of the observer's ingredient channels shows the true ingredient ``perm[j]``, so its 2-bit
    counter takes ingredient ``perm[j]``'s count; the plate and cooked bits stay. Permuting the codes
    before the lookups equals permuting the channels after them (how the reference does it), but
    costs n shifts per cell instead of a gather per channel.
    """
    counts = (code[..., None] >> (2 + 2 * perm)) & 3
    slots = counts << (2 + 2 * jnp.arange(n, dtype=jnp.int32))
    return (code & 3) | slots.sum(axis=-1)  # the fields are disjoint: sum == or


def _permute_codes(config: EnvConfig, codes: jax.Array, perm: jax.Array) -> jax.Array:
    """Cell codes [4, h, w] as seen through ``perm``: piles, items and shown recipes move slot."""
    n = config.num_ingredients
    static_code, items, recipe, pot_timer = codes
    # The slot where the pile's ingredient shows: j with perm[j] == pile (a compare, not a sort).
    pile = static_code - Static.INGREDIENT_PILE
    slots = jnp.arange(n, dtype=jnp.int32)
    slot = jnp.sum(jnp.where(perm[None, None, :] == pile[..., None], slots, 0), axis=-1)
    is_pile = (pile >= 0) & (pile < n)
    static_code = jnp.where(is_pile, Static.INGREDIENT_PILE + slot, static_code)
    return jnp.stack([static_code, _permute_item(items, perm, n), _permute_item(recipe, perm, n), pot_timer])


def _item_chunk_tables(n: int, offset: int, total: int) -> list[np.ndarray]:
    """Tables mapping each 8-bit chunk of an item to its item-block channels at ``offset``.

    Two-bit counters start at even bits, so none straddles a chunk; summing the chunk rows gives the
    whole item block. (Splitting keeps tables small for any number of ingredients.)
    """
    tables = []
    for chunk in range(_num_chunks(n)):
        table = np.zeros((256, total), np.int32)
        values = np.arange(256) << (8 * chunk)
        fields = [(0, 1), (1, 1)] + [(2 + 2 * i, 3) for i in range(n)]
        for channel, (shift, mask) in enumerate(fields):
            if 8 * chunk <= shift < 8 * chunk + 8:
                table[:, offset + channel] = (values >> shift) & mask
        tables.append(table)
    return tables


# Rows of the "look" table. A cell's look code is its static id, except where a second plane shows:
# pots look up the row of their timer, recipe indicators and active buttons the row of their recipe's
# low byte (the timer and the recipe show nowhere else). One gather then covers what the raw codes
# need three for (static, recipe, timer).
_NUM_STATIC = Static.INGREDIENT_PILE + 16  # static ids, 16 pile slots
_LIT_GOAL = _NUM_STATIC  # a goal showing the successful-delivery flag (a raw code too)
_POT = _LIT_GOAL + 1  # + pot timer (0..255)
_INDICATOR = _POT + 256  # + the recipe's low byte
_ACTIVE_BUTTON = _INDICATOR + 256  # + the recipe's low byte
_NUM_LOOKS = _ACTIVE_BUTTON + 256


@functools.lru_cache(maxsize=64)
def _shared_tables(config: EnvConfig):
    """Constant lookup tables (in the observation dtype) for the channels every observer shares.

    ``look`` serves both code kinds: raw static codes (< ``_POT``) index its first rows.
    """
    dtype = np.dtype(config.obs_dtype)
    n = config.num_ingredients
    total = full_channels(config)
    look = np.zeros((_NUM_LOOKS, total), np.int32)
    for channel, static_id in enumerate(_STATIC_CHANNELS):
        look[static_id, 14 + 2 * n + channel] = 1
    for i in range(n):
        look[Static.INGREDIENT_PILE + i, 20 + 2 * n + i] = 1
    look[_LIT_GOAL] = look[Static.GOAL]
    if config.indicate_successful_delivery:
        look[_LIT_GOAL, 25 + 5 * n] = 1
    timer = np.zeros((256, total), np.int32)
    timer[:, 24 + 5 * n] = np.arange(256)
    recipe = _item_chunk_tables(n, 22 + 4 * n, total)
    look[_POT : _POT + 256] = look[Static.POT] + timer
    look[_INDICATOR : _INDICATOR + 256] = look[Static.RECIPE_INDICATOR] + recipe[0]
    look[_ACTIVE_BUTTON : _ACTIVE_BUTTON + 256] = look[Static.BUTTON] + recipe[0]
    return dict(
        look=look.astype(dtype),
        items=[t.astype(dtype) for t in _item_chunk_tables(n, 20 + 3 * n, total)],
        recipe=[t.astype(dtype) for t in recipe],
        timer=timer.astype(dtype),
    )


def _agent_row(config: EnvConfig, direction, inventory, offset: int) -> jax.Array:
    """One agent's layer values at its own cell: position, direction one-hot, item block -> [C]."""
    n = config.num_ingredients
    features = jnp.concatenate(
        [jnp.ones((1,), jnp.int32), jax.nn.one_hot(direction, 4, dtype=jnp.int32), it.item_channels(inventory, n)]
    )
    row = jnp.zeros((full_channels(config),), jnp.int32).at[offset : offset + 7 + n].set(features)
    return row.astype(config.obs_dtype)


def _seen_codes(config: EnvConfig, state: State, codes: jax.Array, observer: int) -> jax.Array:
    """Cell codes [4, h, w] as ``observer`` sees them (ingredient order permuted under other-play)."""
    if not config.op_enabled:
        return codes
    return _permute_codes(config, codes, state.ingredient_permutations[observer])


def _seen_inventory(config: EnvConfig, state: State, observer: int, agent: int) -> jax.Array:
    """Agent ``agent``'s held item as ``observer`` sees it (ingredient order permuted under other-play)."""
    inventory = state.agents.inventory[agent]
    if not config.op_enabled:
        return inventory
    return _permute_item(inventory, state.ingredient_permutations[observer], config.num_ingredients)


def _cell_codes(config: EnvConfig, state: State) -> jax.Array:
    """Raw per-cell codes [4, H, W]: static id (or lit goal), item, shown recipe, pot timer (0 elsewhere)."""
    static, items, timer = state.grid[:, :, 0], state.grid[:, :, 1], state.grid[:, :, 2]
    lit = (static == Static.GOAL) & state.new_correct_delivery if config.indicate_successful_delivery else False
    static_code = jnp.where(lit, _LIT_GOAL, jnp.clip(static, 0, _NUM_STATIC - 1))
    shows_recipe = (static == Static.RECIPE_INDICATOR) | ((static == Static.BUTTON) & (timer > 0))
    return jnp.stack(
        [
            static_code,
            items,
            jnp.where(shows_recipe, state.recipe, 0),
            jnp.where(static == Static.POT, jnp.clip(timer, 0, 255), 0),
        ]
    )


def _look_codes(config: EnvConfig, codes: jax.Array) -> jax.Array:
    """Raw codes [4, h, w] -> look codes [2, h, w] (look, item), or [3, h, w] (+ recipe) when the
    recipe has more than one byte (n >= 4). Zero codes (cells off the map) stay zero: a zero row."""
    static_code, items, recipe, pot_timer = codes
    low_recipe = recipe & 0xFF
    look = jnp.where(static_code == Static.POT, _POT + pot_timer, static_code)
    look = jnp.where(static_code == Static.RECIPE_INDICATOR, _INDICATOR + low_recipe, look)
    # An idle button shows recipe 0, whose row is the bare button's: the same either way.
    look = jnp.where(static_code == Static.BUTTON, _ACTIVE_BUTTON + low_recipe, look)
    planes = [look, items] + ([recipe] if _num_chunks(config.num_ingredients) > 1 else [])
    return jnp.stack(planes)


def _num_chunks(n: int) -> int:
    """8-bit chunks of an item or recipe code (2 + 2n bits)."""
    return (2 + 2 * n + 7) // 8


def _byte(code: jax.Array, chunk: int) -> jax.Array:
    return (code >> (8 * chunk)) & 0xFF


def _lookup_raw(tables, codes: jax.Array) -> jax.Array:
    """Shared channels [h, w, C] from raw codes [4, h, w]: four table rows per cell (n <= 3)."""
    static_code, items, recipe, pot_timer = codes
    obs = jnp.asarray(tables["look"])[static_code] + jnp.asarray(tables["timer"])[pot_timer]
    for chunk, (t_item, t_recipe) in enumerate(zip(tables["items"], tables["recipe"])):
        obs = obs + jnp.asarray(t_item)[_byte(items, chunk)] + jnp.asarray(t_recipe)[_byte(recipe, chunk)]
    return obs


def _lookup_looks(tables, looks: jax.Array) -> jax.Array:
    """Shared channels [h, w, C] from look codes [2 or 3, h, w]: two table rows per cell (n <= 3)."""
    obs = jnp.asarray(tables["look"])[looks[0]]
    for chunk, t_item in enumerate(tables["items"]):
        obs = obs + jnp.asarray(t_item)[_byte(looks[1], chunk)]
    for chunk in range(1, len(tables["recipe"])):
        obs = obs + jnp.asarray(tables["recipe"][chunk])[_byte(looks[2], chunk)]
    return obs


def grid_observations(config: EnvConfig, state: State) -> jax.Array:
    """Every agent's default observation [N, h, w, C] (view window applied, before paper truncation)."""
    if config.view_radius is None:
        return _full_view(config, state)
    return _windowed_view(config, state)


def _full_view(config: EnvConfig, state: State) -> jax.Array:
    """Whole-map observations: the shared channels once, then each agent's layers added at its cell.

    The lookup reads the raw codes: here they are computed inside the lookup fusion, so folding them
    into look codes (as the windowed view does) measured no faster.
    """
    n = config.num_ingredients
    agents = state.agents
    num_agents = agents.x.shape[0]
    tables = _shared_tables(config)
    codes = _cell_codes(config, state)
    shared = None if config.op_enabled else _lookup_raw(tables, codes)
    out = []
    for o in range(num_agents):
        # Other-play: each observer sees its own ingredient order, so its own lookup.
        obs = _lookup_raw(tables, _seen_codes(config, state, codes, o)) if shared is None else shared
        rows = jnp.stack(
            [
                _agent_row(config, agents.dir[b], _seen_inventory(config, state, o, b), 0 if b == o else 7 + n)
                for b in range(num_agents)
            ]
        )
        # One scatter of every agent's row into the materialised shared channels: a masked add (or a
        # lookup of agent codes) lets XLA split the shared lookup into one materialised gather per
        # table, and one scatter per agent costs several kernels each at batch 1.
        obs = obs.at[agents.y, agents.x].add(rows)
        out.append(obs)
    return jnp.stack(out)


def _windowed_view(config: EnvConfig, state: State) -> jax.Array:
    """View-window observations, built from the window's cell codes rather than cut from a full one.

    Cutting the codes (zero outside the map, which looks up all-zero rows, like the reference's zero
    padding) and looking up only the window's cells does a fraction of the work of building every
    cell's C channels and slicing. The cut codes are look codes (two planes, so two gathers per cell
    instead of four), except under other-play, which permutes the raw codes per observer. Agents' layers are masked adds
    (agents never share a cell), not scatters.
    """
    n = config.num_ingredients
    agents = state.agents
    num_agents = agents.x.shape[0]
    tables = _shared_tables(config)
    radius = config.view_radius
    side = 2 * radius + 1
    codes = _cell_codes(config, state)
    if not config.op_enabled:
        codes = _look_codes(config, codes)
    planes = codes.shape[0]
    codes = jnp.pad(codes, ((0, 0), (radius, radius), (radius, radius)))
    windows = jax.vmap(lambda y, x: jax.lax.dynamic_slice(codes, (0, y, x), (planes, side, side)))(agents.y, agents.x)
    # Map coordinates of every window cell, per observer.
    cell_y = agents.y[:, None, None] - radius + jnp.arange(side, dtype=jnp.int32)[None, :, None]
    cell_x = agents.x[:, None, None] - radius + jnp.arange(side, dtype=jnp.int32)[None, None, :]
    out = []
    for o in range(num_agents):
        window = windows[o]
        if config.op_enabled:
            window = _look_codes(config, _seen_codes(config, state, window, o))
        obs = _lookup_looks(tables, window)
        for b in range(num_agents):
            row = _agent_row(config, agents.dir[b], _seen_inventory(config, state, o, b), 0 if b == o else 7 + n)
            on_cell = (cell_y[o] == agents.y[b]) & (cell_x[o] == agents.x[b])
            obs = obs + on_cell.astype(row.dtype)[:, :, None] * row
        out.append(obs)
    return jnp.stack(out)


def default_observations(config: EnvConfig, state: State) -> jax.Array:
    """Every agent's default observation: [N, h, w, C]."""
    obs = grid_observations(config, state)
    channels = num_channels(config)
    if obs.shape[-1] != channels:
        obs = obs[..., :channels]
    return obs
