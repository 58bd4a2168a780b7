"""The environment state: a flax struct pytree with fixed shapes for a given layout.

Unlike the reference, ``ingredient_permutations`` is always an array (the identity when other-play
is off), so states of every env variant share one pytree structure and can be stacked, archived and
used as reset buffers interchangeably.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Agents:
    """Per-agent arrays, leading axis = agent index (N)."""

    x: jax.Array  # int32[N] column
    y: jax.Array  # int32[N] row
    dir: jax.Array  # int32[N] facing Direction
    inventory: jax.Array  # int32[N] held item encoding


@struct.dataclass
class State:
    """One kitchen at one time step.

    ``grid`` is int32[H, W, 3]: layer 0 the static id, layer 1 the item on the cell (counter item or
    pot contents), layer 2 the pot timer (cooking steps left) on pots and the button timer on buttons.
    """

    agents: Agents
    grid: jax.Array  # int32[H, W, 3]
    recipe: jax.Array  # int32[] current order (ingredient units, no flags)
    step: jax.Array  # int32[] transitions taken in this episode
    done: jax.Array  # bool[]
    new_correct_delivery: jax.Array  # bool[] a correct dish was delivered in the last transition
    ingredient_permutations: jax.Array  # int32[N, n] per-agent observation permutation (other-play)


def stack_states(states) -> State:
    """Stack a list of same-layout states along a new leading axis (a reset buffer)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


def num_states(buffer: State) -> int:
    """Number of states in a batched state (its leading axis)."""
    return int(buffer.step.shape[0])
