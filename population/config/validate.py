"""Range checks of a parsed config: values against each other and against the environment they train in.

Each function returns every problem it finds (``section.key: what is wrong``); ``parse_config`` reports them
together with the type errors, so ``ocv2 validate`` lists them all at once.
"""

from __future__ import annotations

from ocv2.config import build_config
from population.config.fields import INT32
from population.config.schema import (
    ACTIVATIONS,
    FCP_POOLS,
    FCP_STAGE_SEED_OFFSET,
    GRU_BACKWARDS,
    KERNELS,
    MAX_GRU_UNROLL,
    MAX_SEED,
    METHODS,
    PRECISIONS,
    ClusterConfig,
    Config,
    FCPConfig,
    PopulationConfig,
    PPOConfig,
    is_update_number,
)


def _positive(key: str, value, allow_zero: bool = False) -> list[str]:
    if value < 0 or (value == 0 and not allow_zero):
        return [f"{key}: must be {'>= 0' if allow_zero else '> 0'}, got {value}"]
    return []


def ppo_problems(prefix: str, ppo: PPOConfig) -> list[str]:
    """Range checks of a ppo section (``prefix``: where it sits, e.g. ppo or population.fcp.partner_ppo)."""
    problems: list[str] = []
    if ppo.activation not in ACTIVATIONS:
        problems.append(f"{prefix}.activation: expected one of {', '.join(ACTIVATIONS)}, got {ppo.activation!r}")
    for key in (
        "lr",
        "clip_eps",
        "max_grad_norm",
        "num_envs",
        "num_steps",
        "num_minibatches",
        "update_epochs",
        "total_timesteps",
    ):
        problems += _positive(f"{prefix}.{key}", getattr(ppo, key))
    for key in ("ent_coef", "vf_coef", "rew_shaping_horizon"):
        problems += _positive(f"{prefix}.{key}", getattr(ppo, key), allow_zero=True)
    for key in ("gamma", "gae_lambda", "lr_warmup"):
        if not 0.0 <= getattr(ppo, key) <= 1.0:
            problems.append(f"{prefix}.{key}: must lie in [0, 1], got {getattr(ppo, key)}")
    if ppo.num_envs > 0 and ppo.num_steps > 0 and ppo.num_updates < 1:
        problems.append(
            f"{prefix}.total_timesteps: {ppo.total_timesteps} is less than one update "
            f"(num_envs x num_steps = {ppo.steps_per_update})"
        )
    if ppo.schedule_timesteps is not None and ppo.schedule_timesteps < ppo.total_timesteps:
        problems.append(
            f"{prefix}.schedule_timesteps: {ppo.schedule_timesteps} is less than total_timesteps "
            f"({ppo.total_timesteps}); a schedule can be stopped early (truncated), not overrun"
        )
    # Training counts env steps and optimiser steps in int32 arrays: past 2**31 they would wrap negative.
    high = INT32[1]
    if ppo.steps_per_update > high:
        problems.append(
            f"{prefix}.num_envs: num_envs x num_steps = {ppo.steps_per_update:,} env steps per update "
            f"exceed the int32 step counter ({high:,})"
        )
    # Updates are env steps over num_envs x num_steps: a zero of either is named above, not divided by here.
    optimiser_steps = ppo.schedule_updates * ppo.update_epochs * ppo.num_minibatches if ppo.steps_per_update > 0 else 0
    if optimiser_steps > high:
        problems.append(
            f"{prefix}.total_timesteps: {ppo.schedule_updates:,} updates x {ppo.update_epochs} epochs x "
            f"{ppo.num_minibatches} minibatches = {optimiser_steps:,} optimiser steps exceed the int32 "
            f"step counter ({high:,})"
        )
    return problems


def _validate_fcp(fcp: FCPConfig, num_agents: int, activation: str) -> list[str]:
    """``activation``: the learner's (``ppo.activation``), the one its network plays the partners with."""
    problems = _positive("population.fcp.partner_seeds", fcp.partner_seeds)
    if fcp.partners is not None and not str(fcp.partners).strip():
        problems.append(
            "population.fcp.partners: empty; give an SP run directory, or leave it out (null) to train the partners first"
        )
    if fcp.pool not in FCP_POOLS:
        problems.append(f"population.fcp.pool: expected one of {', '.join(FCP_POOLS)}, got {fcp.pool!r}")
    if not fcp.checkpoints:
        problems.append("population.fcp.checkpoints: needs at least one checkpoint")
    for c in fcp.checkpoints:
        if c not in ("init", "mid", "final") and not is_update_number(c):
            problems.append(f"population.fcp.checkpoints: {c!r} is not init, mid, final or an update number")
    if num_agents != 2:
        problems.append("population.method: fcp needs a two-agent layout")
    partner = fcp.partner_ppo
    if partner is None:
        return problems
    key = "population.fcp.partner_ppo"
    partner_problems = ppo_problems(key, partner)
    problems += partner_problems
    if partner_problems or fcp.partners:  # the checks below divide by these sizes, and are of a stage that trains
        return problems
    if partner.activation != activation:
        problems.append(
            f"{key}.activation: {partner.activation!r}, but ppo.activation is {activation!r}: the learner plays its "
            "partners with its own network, so they must train with the same activation (leave it out to inherit it)"
        )
    if (partner.num_envs * num_agents) % partner.num_minibatches:
        problems.append(
            f"{key}.num_minibatches: {partner.num_minibatches} does not divide the "
            f"{partner.num_envs * num_agents} self-play sequences per update of the partner stage "
            f"(num_envs x {num_agents} agents)"
        )
    return problems


def validate(config: Config) -> list[str]:
    """Every problem of values checked against each other (each value has the right type already)."""
    model, ppo, pop = config.model, config.ppo, config.population
    problems: list[str] = []
    if len(model.conv_features) != len(model.conv_kernels):
        problems.append("model.conv_kernels: needs one kernel size per entry of model.conv_features")
    if model.kernels not in KERNELS:
        problems.append(f"model.kernels: expected one of {', '.join(KERNELS)}, got {model.kernels!r}")
    if model.gru_backward not in GRU_BACKWARDS:
        problems.append(f"model.gru_backward: expected one of {', '.join(GRU_BACKWARDS)}, got {model.gru_backward!r}")
    if not 1 <= model.gru_unroll <= MAX_GRU_UNROLL:
        problems.append(
            f"model.gru_unroll: expected 1 to {MAX_GRU_UNROLL} time steps per iteration, got {model.gru_unroll}"
        )
    for key in ("fc_dim", "gru_dim"):
        problems += _positive(f"model.{key}", getattr(model, key))
    for key, values in (
        ("conv_features", model.conv_features),
        ("conv_kernels", model.conv_kernels),
        ("mixer_features", model.mixer_features),
    ):
        for v in values:
            problems += _positive(f"model.{key}", v)
    problems += ppo_problems("ppo", ppo)
    sizes_ok = ppo.num_envs > 0 and ppo.num_steps > 0 and ppo.num_minibatches > 0
    env = build_config(**config.env_kwargs)
    # The networks read grids: the environment's featurized vectors are for other learners (docs/environment.md).
    if any(kind != "default" for kind in env.observation_types):
        problems.append(
            f"env.observation_type: ocv2's networks train on grid observations ('default'), got "
            f"{config.env_kwargs.get('observation_type')!r}"
        )
    one_seat = pop.method in METHODS and pop.traits.one_learner_seat  # (an unknown name is reported below)
    learner_actors = ppo.num_envs if one_seat else ppo.num_envs * env.num_agents
    if sizes_ok and learner_actors % ppo.num_minibatches:
        seats = "1 learner seat" if one_seat else f"{env.num_agents} agents"
        problems.append(
            f"ppo.num_minibatches: {ppo.num_minibatches} does not divide the {learner_actors} "
            f"learner sequences per update (num_envs x {seats})"
        )
    if pop.method not in METHODS:
        problems.append(f"population.method: expected one of {', '.join(METHODS)}, got {pop.method!r}")
    problems += _positive("population.num_seeds", pop.num_seeds)
    problems += _seed_problems(pop)
    for key in ("iterations", "rollouts_per_pair", "keep_every"):
        problems += _positive(f"population.sa.{key}", getattr(pop.sa, key))
    if pop.method == "sa":
        if sizes_ok and pop.sa.iterations > ppo.schedule_updates:
            problems.append(
                f"population.sa.iterations: {pop.sa.iterations} iterations need at least as many "
                f"updates, the config's schedule has {ppo.schedule_updates}"
            )
        if pop.sa.keep_every > env.max_steps:
            problems.append(f"population.sa.keep_every: {pop.sa.keep_every} exceeds env.max_steps={env.max_steps}")
    if pop.method == "op":
        n = env.num_ingredients
        if len(pop.op.ingredients) < 2 or len(set(pop.op.ingredients)) != len(pop.op.ingredients):
            problems.append("population.op.ingredients: needs at least two distinct ingredient indices")
        if any(not 0 <= i < n for i in pop.op.ingredients):
            problems.append(
                f"population.op.ingredients: indices must lie in [0, {n}) for layout "
                f"{env.layout.name!r}, got {list(pop.op.ingredients)}"
            )
        if env.op_enabled:
            problems.append(
                "env.op_ingredient_permutations: set population.op.ingredients instead "
                "(evaluation must run without permutations)"
            )
    if pop.method == "fcp":
        problems += _validate_fcp(pop.fcp, env.num_agents, ppo.activation)
    problems += _positive("eval.episodes", config.eval.episodes)
    problems += _positive("eval.gifs", config.eval.gifs, allow_zero=True)
    problems += _positive("run.checkpoint_every", config.run.checkpoint_every)
    if config.run.precision not in PRECISIONS:
        problems.append(f"run.precision: expected one of {', '.join(PRECISIONS)}, got {config.run.precision!r}")
    problems += _positive("archive.train_every", config.archive.train_every, allow_zero=True)
    problems += _cluster_problems(config.cluster, pop.num_seeds)
    if config.run.num_checkpoints < 2:
        problems.append(f"run.num_checkpoints: must be >= 2 (initial and final), got {config.run.num_checkpoints}")
    problems += _snapshot_problems(config)
    return problems


#: Snapshots any run may ask for, however few updates it has (a pilot of a study that keeps 11 snapshots
#: trains a handful of updates and keeps every one of them).
MIN_SNAPSHOT_BOUND = 100


def _snapshot_problems(config: Config) -> list[str]:
    """``run.num_checkpoints`` spreads snapshots over updates 0..N: beyond N + 1 they repeat updates, and a
    count of 1e9 would hang the run while their update numbers are computed. Bounded by the most updates
    of any stage the run trains (its own, an FCP partner stage's), or ``MIN_SNAPSHOT_BOUND``."""
    ppo, partner = config.ppo, config.population.fcp.partner_ppo
    stages = [ppo] + ([partner] if config.population.method == "fcp" and partner is not None else [])
    if any(stage.steps_per_update <= 0 for stage in stages):
        return []  # reported by the ppo checks
    updates = max(stage.num_updates for stage in stages)
    bound = max(updates + 1, MIN_SNAPSHOT_BOUND)
    if config.run.num_checkpoints > bound:
        return [
            f"run.num_checkpoints: {config.run.num_checkpoints:,} snapshots of a run of {updates:,} updates; at most "
            f"{bound:,} (the larger of one per update with update 0, {updates + 1:,}, and {MIN_SNAPSHOT_BOUND})"
        ]
    return []


def _seed_problems(pop: PopulationConfig) -> list[str]:
    """Every seed a run derives must fit a 32-bit PRNG seed (larger ones would wrap onto small ones)."""
    if pop.seed < 0:
        return [f"population.seed: must be >= 0, got {pop.seed}"]
    largest = MAX_SEED - (FCP_STAGE_SEED_OFFSET if pop.trains_partners else 0)
    if pop.seed > largest:
        why = " (the FCP partner stage trains with seed + 7919)" if largest < MAX_SEED else ""
        return [f"population.seed: must be <= {largest}{why}, got {pop.seed}"]
    return []


def _cluster_problems(cluster: ClusterConfig, num_seeds: int) -> list[str]:
    problems: list[str] = []
    if cluster.address is not None:
        address = cluster.address.strip()
        host, _, port = address.rpartition(":")
        is_port = is_update_number(port) and int(port) <= 65535  # ASCII digits: "²".isdigit() is True
        if address != "auto" and not (host and is_port) and not address.startswith("ray://"):
            problems.append(f"cluster.address: expected auto, HOST:PORT or ray://HOST:PORT, got {cluster.address!r}")
    problems += _positive("cluster.workers", cluster.workers, allow_zero=True)
    problems += _positive("cluster.seeds_per_actor", cluster.seeds_per_actor)
    if cluster.workers and cluster.seeds_per_actor != 1:
        problems.append("cluster.workers: set either workers or seeds_per_actor, not both")
    if cluster.workers > num_seeds:
        problems.append(f"cluster.workers: {cluster.workers} actors for {num_seeds} seeds (at most one per seed)")
    problems += _positive("cluster.num_cpus", cluster.num_cpus)
    if isinstance(cluster.num_gpus, str):
        if cluster.num_gpus != "auto":
            problems.append(f"cluster.num_gpus: expected auto or a number >= 0, got {cluster.num_gpus!r}")
    else:
        problems += _positive("cluster.num_gpus", cluster.num_gpus, allow_zero=True)
    if not 0.0 <= cluster.gpu_memory_fraction < 1.0:
        problems.append(f"cluster.gpu_memory_fraction: must lie in [0, 1), got {cluster.gpu_memory_fraction}")
    problems += _positive("cluster.max_restarts", cluster.max_restarts, allow_zero=True)
    problems += _positive("cluster.local_cpus", cluster.local_cpus, allow_zero=True)
    return problems
