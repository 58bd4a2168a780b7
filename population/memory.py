"""How much memory a run needs, from measured peaks, against how much this machine has.

A linear model of resident memory (docs/cluster.md, "Memory"): every process that trains seeds holds a
fixed ``BASE_MIB`` (Python, JAX, XLA's compiled programs) plus, per seed it vmaps, the rollout and
its activations, which grow with the env steps per update and the observation size. The per-seed
numbers were measured at the paper's sizes (``bench/memory.py``: peak RSS of one process training 2, 4
and 8 CNN or 2 and 4 RNN seeds for one update) and scale linearly in ``num_envs x num_steps x agents x observation
elements`` to other sizes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os

from ocv2.config import build_config
from ocv2.observations import grid_obs_shape
from population.config import Config, ConfigError, ModelConfig, PPOConfig
from population.config.shards import shard_count

MIB = 2**20


@dataclasses.dataclass(frozen=True)
class Measured:
    """Peak RSS of one process against seeds vmapped in it: ``base_mib + seeds * per_seed_mib``, at the
    sizes of one paper config (``elements``: num_envs x num_steps x agents x observation elements)."""

    config: str
    base_mib: float
    per_seed_mib: float
    elements: int


#: Measured 2026-11-25, x86-64 CPU, jax 0.10.2 (bench/memory.py; docs/cluster.md lists the points).
MEASURED = {
    "cnn": Measured("classic_cramped_room_sp.yaml", base_mib=650, per_seed_mib=129, elements=64 * 256 * 2 * 4 * 5 * 30),
    "rnn": Measured(
        "v2_grounded_coord_simple_sp.yaml", base_mib=1006, per_seed_mib=394, elements=256 * 256 * 2 * 5 * 5 * 40
    ),
}
#: Ray's own processes on a machine that starts it (GCS, raylet, log monitor, dashboard agent), measured
#: in shared notes at 300-400 MB resident.
RAY_SYSTEM_MIB = 400


@dataclasses.dataclass(frozen=True)
class MemoryEstimate:
    """Estimated peak resident memory of a run on this machine (MiB), and how it was counted."""

    total_mib: float
    where: str

    def describe(self) -> str:
        return f"~{_gib(self.total_mib)} ({self.where})"


#: Where the seeds train, as ``estimate`` counts them.
PLACES = ("local", "ray", "cluster")


def per_seed_mib(config: Config, ppo: PPOConfig) -> float:
    """One seed's share of a training process, scaled from the measurement of the same model kind."""
    env = build_config(**config.env_kwargs)
    elements = ppo.num_envs * ppo.num_steps * env.num_agents * math.prod(grid_obs_shape(env))
    measured = MEASURED[config.model.kind]
    return measured.per_seed_mib * elements / measured.elements


def params_mib(config: Config) -> float:
    """One seed's parameters, which the driver gathers for every seed (SA, cross-play)."""
    return _params_mib(config.model, grid_obs_shape(build_config(**config.env_kwargs)))


@functools.lru_cache(maxsize=64)
def _params_mib(model: ModelConfig, obs_shape: tuple[int, ...]) -> float:
    import jax  # here: checking a config (ocv2 validate, ocv2 train before Ray starts) must not start JAX

    from population.networks import init_params, make_network

    network = make_network(model)
    shapes = jax.eval_shape(lambda key: init_params(network, key, obs_shape), jax.random.PRNGKey(0))
    return sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(shapes)) / MIB


def stages(config: Config) -> list[tuple[int, PPOConfig]]:
    """(seeds trained at once, their ppo section) of each training stage: an FCP run trains its partner
    stage first, then the learners."""
    pop = config.population
    runs = [(pop.num_seeds, config.ppo)]
    if pop.trains_partners and pop.fcp.partner_ppo is not None:
        runs.insert(0, (pop.fcp.stage_seeds(pop.num_seeds), pop.fcp.partner_ppo))
    return runs


def estimate(config: Config, place: str = "local") -> MemoryEstimate:
    """Peak memory on this machine when the seeds train ``place``: ``local`` (every seed in this
    process), ``ray`` (a Ray started here: one actor per shard of seeds, the driver and Ray's own
    processes) or ``cluster`` (Ray joined elsewhere: only the driver, holding every seed's parameters)."""
    base = MEASURED[config.model.kind].base_mib
    worst = None
    for seeds, ppo in stages(config):
        if place == "cluster":
            found = MemoryEstimate(
                base + seeds * params_mib(config), f"the driver of {seeds:,} seed{'s' * (seeds != 1)}"
            )
        elif place == "local":
            found = MemoryEstimate(
                base + seeds * per_seed_mib(config, ppo), f"{seeds:,} seed{'s' * (seeds != 1)} in one process"
            )
        else:
            actors = shard_count(
                dataclasses.replace(config, population=dataclasses.replace(config.population, num_seeds=seeds))
            )
            found = MemoryEstimate(
                (actors + 1) * base + seeds * per_seed_mib(config, ppo) + RAY_SYSTEM_MIB,
                f"{seeds:,} seeds in {actors:,} Ray actors, the driver and Ray",
            )
        if worst is None or found.total_mib > worst.total_mib:
            worst = found
    return worst


def machine_memory_mib() -> float | None:
    """This machine's physical memory (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / MIB
    except (AttributeError, ValueError, OSError):
        return None


def check_fits(config: Config, place: str = "local", available_mib: float | None = None) -> MemoryEstimate:
    """The estimate, or a ConfigError when it, or the run's cross-play after training, exceeds this machine's
    memory (``available_mib``, default: its physical memory)."""
    found = estimate(config, place)
    available = machine_memory_mib() if available_mib is None else available_mib
    if available is not None and found.total_mib > available:
        pop = config.population
        fewest = dataclasses.replace(pop, num_seeds=1, fcp=dataclasses.replace(pop.fcp, partner_seeds=1))
        one = estimate(dataclasses.replace(config, population=fewest), place)
        if one.total_mib > available:  # fewer seeds cannot help: the network, batch or observation is too big
            view = config.env_kwargs.get("agent_view_size")
            wide = f", or a smaller env.agent_view_size (observations of {2 * view + 1} cells a side)" if view else ""
            raise ConfigError(
                f"model: one seed alone needs about {_gib(one.total_mib)} of memory on this machine ({one.where}; "
                f"docs/cluster.md, Memory) but it has {_gib(available)}: a smaller network (model.*) or fewer "
                f"ppo.num_envs / ppo.num_steps{wide}"
            )
        advice = "" if place == "cluster" else ", or train on a Ray cluster (--address)"
        raise ConfigError(
            f"population.num_seeds: the run needs about {_gib(found.total_mib)} of memory on this machine "
            f"({found.where}; docs/cluster.md, Memory) but it has {_gib(available)}: lower "
            f"population.num_seeds{' or ppo.num_envs' * (place != 'cluster')}{advice}"
        )
    seeds = config.population.num_seeds  # the run's own cross-play after training: seeds x seeds
    check_crossplay_fits(seeds, seeds, config.eval.episodes, "eval.episodes", available_mib=available)
    return found


#: What cross-play holds per episode until its files are written: the return (float32) and the start recipe (int32),
#: then episodes.csv, built in memory as a row per episode and one text (240-270 bytes an episode at its peak,
#: measured with tracemalloc on 10 x 10 matrices): rounded up.
XP_BYTES_PER_EPISODE = 300


def crossplay_mib(rows: int, cols: int, episodes: int, seats: int = 1) -> float:
    """The per-episode arrays of a ``rows`` x ``cols`` cross-play of ``episodes`` per pair, played in ``seats``
    seatings (``ocv2 xp``'s seat-fair play keeps both)."""
    return rows * cols * episodes * seats * XP_BYTES_PER_EPISODE / MIB


def check_crossplay_fits(
    rows: int, cols: int, episodes: int, key: str, seats: int = 1, available_mib: float | None = None
) -> float:
    """``crossplay_mib``, or a ConfigError naming ``key`` when it exceeds this machine's memory: found at the
    end of a cross-play, or of training, it would be a MemoryError after the hours of play before it."""
    need = crossplay_mib(rows, cols, episodes, seats)
    available = machine_memory_mib() if available_mib is None else available_mib
    if available is not None and need > available:
        seatings = f" in {seats} seatings" if seats > 1 else ""
        raise ConfigError(
            f"{key}: a {rows:,} x {cols:,} cross-play of {episodes:,} episodes per pair{seatings} keeps "
            f"{XP_BYTES_PER_EPISODE} bytes per episode, about {_gib(need)}, but this machine has {_gib(available)}: "
            "play fewer episodes per pair"
        )
    return need


def _gib(mib: float) -> str:
    gib = mib / 1024
    if gib >= 1024**2:
        return f"{gib / 1024**2:,.0f} PiB"
    if gib >= 1024:
        return f"{gib / 1024:,.1f} TiB"
    return f"{gib:,.1f} GiB"
