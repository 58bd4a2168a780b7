"""How seeds, and any other list of jobs, are split into consecutive blocks over workers."""

from __future__ import annotations

import math
from collections.abc import Sequence

from population.config.schema import Config


def spread(items: Sequence, parts: int) -> list[list]:
    """``items`` in ``parts`` consecutive blocks as even as possible (the first ones one longer; some
    empty if there are fewer items than parts)."""
    size, extra = divmod(len(items), parts)
    blocks, start = [], 0
    for index in range(parts):
        end = start + size + (index < extra)
        blocks.append(list(items[start:end]))
        start = end
    return blocks


def shard_count(config: Config) -> int:
    """Worker actors of a run: ``cluster.workers``, else one per ``cluster.seeds_per_actor`` seeds."""
    cluster = config.cluster
    return cluster.workers or math.ceil(config.population.num_seeds / cluster.seeds_per_actor)


def shards(config: Config) -> list[list[int]]:
    """The seeds each Ray worker actor trains: consecutive blocks, as even as possible."""
    return spread(range(config.population.num_seeds), shard_count(config))
