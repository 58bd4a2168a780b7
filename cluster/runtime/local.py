"""The local backend: every seed in one process, vmapped in one jitted program (``--backend local``).

Its ``Workers`` is a single in-process ``SeedShard`` holding the whole population; the coordinator
(``cluster.runtime.coordinator``) is the same one the Ray backend uses, so both write the same run directory.
"""

from __future__ import annotations

from pathlib import Path

from cluster.runtime.jobs import InProcessWorkers
from cluster.runtime.shard import SeedShard
from population.config import Config


class LocalWorkers(InProcessWorkers):
    """One shard with every seed, called directly (nothing to copy)."""

    def __init__(self, config: Config, run_dir: Path, pool=None):
        seeds = list(range(config.population.num_seeds))
        super().__init__([seeds], SeedShard(config, run_dir, seeds, pool))
