"""State augmentation (paper Algorithm 1): a reset buffer built from the population's cross-play.

Before each of ``sa.iterations`` training chunks, every ordered pair (i, j) of the current policies,
self-pairs included, plays ``sa.rollouts_per_pair`` episodes; every ``sa.keep_every``-th state is kept.
Training then resets every episode from a uniform draw of that buffer (the env's ``state_buffer``).

Collection is split per pair so a coordinator can spread pairs over workers: a pair's states depend
only on (key, i, j), never on which worker or in which batch it ran. ``merge_buffers`` concatenates
pair results in pair order, so the buffer is identical however the work was split.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ocv2.state import State
from population.config import SAConfig
from population.evaluation import PolicyApply, gather_params, play_pairs
from population.record import jitted_play_recorded_pairs


class PairStates(NamedTuple):
    pairs: tuple[tuple[int, int], ...]  # (seat-0 policy, seat-1 policy) per block
    states: State  # [len(pairs), R * S, ...] states of each pair, flattened over episodes and time


def all_pairs(num_policies: int) -> list[tuple[int, int]]:
    """Every ordered pair including self-pairs, row-major: (0,0), (0,1), ..., (K-1,K-1)."""
    return [(i, j) for i in range(num_policies) for j in range(num_policies)]


def pair_key(key: jax.Array, pair: tuple[int, int], num_policies: int) -> jax.Array:
    return jax.random.fold_in(key, pair[0] * num_policies + pair[1])


def collect_pair_states(
    apply: PolicyApply,
    hidden_size: int,
    env,
    params,
    key: jax.Array,
    sa: SAConfig,
    pairs: Sequence[tuple[int, int]] | None = None,
) -> PairStates:
    """Play the given ordered pairs of the K stacked ``params`` and keep every ``keep_every``-th state."""
    return collect_pairs(apply, hidden_size, env, params, key, sa, pairs)[0]


def collect_pairs(
    apply: PolicyApply,
    hidden_size: int,
    env,
    params,
    key: jax.Array,
    sa: SAConfig,
    pairs: Sequence[tuple[int, int]] | None = None,
    record: bool = False,
):
    """``(PairStates, Recorded | None)``: the kept states and, with ``record``, every transition.

    Recording plays the very same episodes (same keys, same ``play_step``) and keeps everything; the
    kept states are then its states at t = 0, k, 2k, ..., so the buffer does not depend on ``record``.
    """
    num = jax.tree.leaves(params)[0].shape[0]
    pairs = tuple(all_pairs(num) if pairs is None else (tuple(p) for p in pairs))
    for i, j in pairs:
        if not (0 <= i < num and 0 <= j < num):
            raise ValueError(f"pair ({i}, {j}) is out of range for {num} policies")
    if record:
        play = jitted_play_recorded_pairs(apply, hidden_size, env, sa.rollouts_per_pair)
        kept_steps = env.max_steps // sa.keep_every * sa.keep_every
    else:
        play = _jitted_collect(apply, hidden_size, env, sa.rollouts_per_pair, sa.keep_every)
    blocks, records = [], []
    for start in range(0, len(pairs), max(num, 1)):  # at most K parameter copies per call
        chunk = pairs[start : start + num]
        keys = jnp.stack([pair_key(key, p, num) for p in chunk])
        result = play(gather_params(params, [p[0] for p in chunk]), gather_params(params, [p[1] for p in chunk]), keys)
        if record:
            records.append(result)
            kept = jax.tree.map(lambda x: x[:, :, 0 : kept_steps : sa.keep_every], result.states)
        else:
            kept = result.states
        blocks.append(jax.tree.map(lambda x: x.reshape((x.shape[0], -1) + x.shape[3:]), kept))
    concat = lambda parts: jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
    return PairStates(pairs, concat(blocks)), (concat(records) if record else None)


@functools.lru_cache(maxsize=16)
def _jitted_collect(apply, hidden_size, env, episodes, keep_every):
    return jax.jit(lambda a, b, k: play_pairs(apply, hidden_size, env, a, b, k, episodes, keep_every))


def merge_buffers(parts: Sequence[PairStates]) -> State:
    """One reset buffer [P * R * S] from pair results, ordered by pair (independent of the split)."""
    blocks = {}
    for part in parts:
        for index, pair in enumerate(part.pairs):
            blocks[pair] = jax.tree.map(lambda x: x[index], part.states)
    ordered = [blocks[p] for p in sorted(blocks)]
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *ordered)


def collect_buffer(apply: PolicyApply, hidden_size: int, env, params, key: jax.Array, sa: SAConfig) -> State:
    """The whole buffer of one SA iteration in one process."""
    return merge_buffers([collect_pair_states(apply, hidden_size, env, params, key, sa)])


def extend_buffer(buffer: State, extra: State | None) -> State:
    """The collected buffer followed by states from elsewhere (an archive: ``cluster.archive.states_as_buffer``)."""
    if extra is None:
        return buffer
    return jax.tree.map(
        lambda a, b: np.concatenate([np.asarray(a), np.asarray(b, dtype=np.asarray(a).dtype)]), buffer, extra
    )


def buffer_size(num_policies: int, sa: SAConfig, max_steps: int) -> int:
    return num_policies * num_policies * sa.rollouts_per_pair * (max_steps // sa.keep_every)


def to_numpy(buffer: State) -> State:
    return jax.tree.map(np.asarray, buffer)
