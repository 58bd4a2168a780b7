"""The local backend: every seed in one process, vmapped in one jitted program (``--backend local``).

Its ``Workers`` is a single in-process ``SeedShard`` holding the whole population; the coordinator
(``cluster.runtime.coordinator``) is the same one the Ray backend uses, so both write the same run directory.
"""

from __future__ import annotations

from pathlib import Path

from cluster.runtime import coordinator
from cluster.runtime.jobs import InProcessWorkers
from cluster.runtime.shard import SeedShard
from population.config import Config


class LocalWorkers(InProcessWorkers):
    """One shard with every seed, called directly (nothing to copy)."""

    def __init__(self, config: Config, run_dir: Path, pool=None):
        seeds = list(range(config.population.num_seeds))
        super().__init__([seeds], SeedShard(config, run_dir, seeds, pool))


def train_population(
    config: Config,
    run_dir,
    *,
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    label: str | None = None,
) -> dict:
    """Train (or resume) a population into ``run_dir`` in this process; then cross-play, plots, GIFs, archive."""
    return coordinator.train(
        config, run_dir, LocalWorkers, resume=resume, show_progress=show_progress, evaluate=evaluate, label=label
    )
