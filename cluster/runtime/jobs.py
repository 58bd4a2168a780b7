"""What the coordinator and the evaluation ask of a backend, and how they split work into jobs.

A backend's ``Workers`` runs ``SeedShard`` methods on its shards (``cluster.runtime.local``: one
in-process shard; ``cluster.runtime.ray_backend``: one actor per shard). Population-wide work (SA
collection pairs, cross-play rows) is spread over the shards in consecutive blocks; each job's
result depends only on its arguments, so the split never changes a number.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import jax
import numpy as np

from cluster.runtime.environment import process_record
from population.config import Config, spread


class Workers(Protocol):
    """What the coordinator needs from a backend."""

    shards: list[list[int]]  # seed indices of each shard

    def call(self, method: str, jobs: Sequence[tuple[int, tuple]]) -> list:
        """Run ``SeedShard.<method>(*args)`` for each (shard index, args); results in job order."""

    def share(self, value):
        """A handle to pass ``value`` to many calls without copying it per call (Ray: ``ray.put``)."""

    def restarts(self) -> int:
        """Worker restarts so far (0 for in-process shards)."""

    events: list[dict]  # one per worker death: shard, seeds, method, restored_update

    def describe(self) -> list[dict]:
        """Per shard, where it trains (``cluster.runtime.environment.process_record`` and more)."""

    def close(self) -> None: ...


WorkersFactory = Callable[[Config, Path, object], Workers]  # (config, run_dir, FCP pool or None)


class InProcessWorkers:
    """``Workers`` with one in-process worker, ``target``, called directly; ``share`` is the identity.

    The local backend (a ``SeedShard``) and local cross-play (a ``CrossPlayPlayer``) both use it.
    """

    def __init__(self, shards: list[list[int]], target):
        self.shards, self.events, self.target = shards, [], target

    def call(self, method: str, jobs):
        return [getattr(self.target, method)(*args) for _, args in jobs]

    def share(self, value):
        return value

    def restarts(self) -> int:
        return 0

    def describe(self) -> list[dict]:
        """This process, once per shard (all of them train here)."""
        return [{**process_record(), "worker": "this process", "num_gpus": None} for _ in self.shards]

    def close(self) -> None:
        self.target = None


def spread_jobs(workers: Workers, items: Sequence, make_args: Callable[[list], tuple]) -> list[tuple[int, tuple]]:
    """One job per non-empty block of ``items``: (shard index, ``make_args(block)``)."""
    return [(shard, make_args(block)) for shard, block in enumerate(spread(items, len(workers.shards))) if block]


def in_waves(workers: Workers, items: Sequence) -> list[list[tuple[int, object]]]:
    """``items`` spread over the shards in consecutive blocks (as ``spread_jobs``), dealt into waves of at most one
    (shard index, item) per shard: calling the workers wave by wave lets a progress bar move as items finish."""
    by_shard = [[(shard, item) for item in block] for shard, block in spread_jobs(workers, items, lambda b: b)]
    return [[queue[w] for queue in by_shard if w < len(queue)] for w in range(max(map(len, by_shard), default=0))]


def on_every_shard(workers: Workers, *args) -> list[tuple[int, tuple]]:
    """The same arguments for every shard."""
    return [(shard, args) for shard in range(len(workers.shards))]


def gather_params(workers: Workers):
    """All seeds' current params stacked in seed order (numpy)."""
    parts = workers.call("params", on_every_shard(workers))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
