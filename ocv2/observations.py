"""Grid observations (spec section 10): per-agent (H, W, C) channel stacks, optional view window.

Channel order (n ingredients, item block = [plate bit, cooked bit, count_0 .. count_{n-1}]):
ego position, ego direction (4), ego inventory block, other agents' position / directions / inventory
blocks (summed), static one-hots (counter, goal, pot, recipe indicator, button, plate pile),
ingredient piles (n), grid item block, recipe block (at indicators and active buttons), pot timer,
and, with ``indicate_successful_delivery``, the delivery flag at goals. C = 25 + 5n (+1).

Values equal the reference's; the dtype is uint8 by default (the reference uses int32).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.config import EnvConfig
from ocv2.items import Static
from ocv2.state import State

_STATIC_CHANNELS = (Static.WALL, Static.GOAL, Static.POT, Static.RECIPE_INDICATOR, Static.BUTTON, Static.PLATE_PILE)


def num_channels(config: EnvConfig) -> int:
    """Channels of the default observation, after the optional paper truncation."""
    n = config.num_ingredients
    full = 25 + 5 * n + int(config.indicate_successful_delivery)
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


def _permutation_index(config: EnvConfig, permutations: jax.Array) -> jax.Array:
    """Per-agent channel gather index that applies each agent's ingredient mapping (other-play)."""
    n = config.num_ingredients
    base = np.arange(25 + 5 * n + int(config.indicate_successful_delivery))
    # Offsets of every block whose ingredient channels are permuted.
    count_starts = [7, 14 + n, 22 + 3 * n, 24 + 4 * n]  # ego inv, other inv, grid items, recipe
    pile_start = 20 + 2 * n
    index = jnp.broadcast_to(jnp.asarray(base), (permutations.shape[0], base.size))
    for start in count_starts + [pile_start]:
        index = index.at[:, start:start + n].set(start + permutations)
    return index


def grid_observations(config: EnvConfig, state: State) -> jax.Array:
    """Full-map observation of every agent: [N, H, W, C] (before the view window)."""
    dtype = jnp.dtype(config.obs_dtype)
    n = config.num_ingredients
    grid = state.grid
    static, items, timer = grid[:, :, 0], grid[:, :, 1], grid[:, :, 2]
    height, width = static.shape
    agents = state.agents

    # Agent layers: [N, H, W, 7 + n] = position, direction one-hot, inventory block at the agent's cell.
    at_agent = (jnp.arange(height)[None, :, None] == agents.y[:, None, None]) & (
        jnp.arange(width)[None, None, :] == agents.x[:, None, None]
    )
    features = jnp.concatenate(
        [
            jnp.ones((agents.x.shape[0], 1), jnp.int32),
            jax.nn.one_hot(agents.dir, 4, dtype=jnp.int32),
            it.item_channels(agents.inventory, n),
        ],
        axis=-1,
    )
    agent_layers = (at_agent[..., None] * features[:, None, None, :]).astype(dtype)
    others = jnp.sum(agent_layers, axis=0, keepdims=True, dtype=dtype) - agent_layers

    shared = [static[..., None] == jnp.asarray(_STATIC_CHANNELS, jnp.int32)]
    shared.append(static[..., None] == (Static.INGREDIENT_PILE + jnp.arange(n, dtype=jnp.int32)))
    shared.append(it.item_channels(items, n))
    shows_recipe = (static == Static.RECIPE_INDICATOR) | ((static == Static.BUTTON) & (timer > 0))
    shared.append(it.item_channels(jnp.where(shows_recipe, state.recipe, 0), n))
    shared.append(jnp.where(static == Static.POT, timer, 0)[..., None])
    if config.indicate_successful_delivery:
        shared.append(((static == Static.GOAL) & state.new_correct_delivery)[..., None])
    shared = jnp.concatenate([s.astype(dtype) for s in shared], axis=-1)

    num_agents = agents.x.shape[0]
    obs = jnp.concatenate(
        [agent_layers, others, jnp.broadcast_to(shared, (num_agents,) + shared.shape)], axis=-1
    )
    if config.op_enabled:
        index = _permutation_index(config, state.ingredient_permutations)
        obs = jnp.take_along_axis(obs, index[:, None, None, :], axis=-1)
    return obs


def view_window(config: EnvConfig, obs: jax.Array, state: State) -> jax.Array:
    """Cut each agent's (2v+1)^2 window centred on it; off-map cells are all zero."""
    radius = config.view_radius
    if radius is None:
        return obs
    padded = jnp.pad(obs, ((0, 0), (radius, radius), (radius, radius), (0, 0)))
    side = 2 * radius + 1

    def cut(agent_obs, y, x):
        return jax.lax.dynamic_slice(agent_obs, (y, x, 0), (side, side, agent_obs.shape[-1]))

    return jax.vmap(cut)(padded, state.agents.y, state.agents.x)


def default_observations(config: EnvConfig, state: State) -> jax.Array:
    """Every agent's default observation: [N, h, w, C]."""
    obs = view_window(config, grid_observations(config, state), state)
    channels = num_channels(config)
    if obs.shape[-1] != channels:
        obs = obs[..., :channels]
    return obs
