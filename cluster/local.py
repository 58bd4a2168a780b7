"""The local backend: a whole population in one process, seeds vmapped in one jitted program.

``train_population(config, run_dir)`` drives SP / SA / OP / FCP in chunks of updates, checkpointing
every ``run.checkpoint_every`` updates, then evaluates cross-play and writes plots and GIFs. The Ray
backend reuses the same run directory and the same ``population`` functions.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from cluster.progress import PopulationProgress
from cluster.rundir import RunDir, RunDirError, metric_rows, write_csv, write_json
from population import checkpoints as ckpt
from population import ppo
from population.config import Config
from population.evaluation import gather_params, play_episodes, stack_params
from population.sa import collect_buffer
from population.xp import cross_play, recipe_names, summarize

SA_KEY_OFFSET = 1 << 20
XP_KEY_OFFSET = 1 << 21
GIF_KEY_OFFSET = 1 << 22


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Where training must stop: snapshots, SA iteration starts, periodic checkpoints."""

    num_updates: int
    snapshots: tuple[int, ...]
    iteration_starts: tuple[int, ...]  # SA only; () otherwise
    checkpoint_every: int

    @staticmethod
    def of(config: Config) -> "Schedule":
        updates = config.ppo.num_updates
        starts = ()
        if config.population.method == "sa":
            iterations = config.population.sa.iterations
            starts = tuple(sorted({round(i * updates / iterations) for i in range(iterations)}))
        return Schedule(updates, tuple(ckpt.snapshot_updates(updates, config.run.num_checkpoints)), starts,
                        config.run.checkpoint_every)

    def next_stop(self, update: int) -> int:
        candidates = [b for b in (*self.snapshots, *self.iteration_starts) if b > update]
        candidates.append((update // self.checkpoint_every + 1) * self.checkpoint_every)
        return min(min(candidates), self.num_updates)

    def iteration_at(self, update: int) -> int:
        return max(i for i, start in enumerate(self.iteration_starts) if start <= update)


def hidden_size(trainer: ppo.Trainer) -> int:
    return trainer.network.gru_dim if trainer.network.recurrent else 0


def _state_template(trainer: ppo.Trainer, pool_size: int):
    return jax.eval_shape(lambda k: ppo.init_train_state(trainer, k, None, pool_size), jax.random.PRNGKey(0))


def _params_template(trainer: ppo.Trainer):
    return _state_template(trainer, 1 if trainer.fcp else 0).params


def _load_params(path, fingerprint: str, template):
    """Only the network parameters of a seed's checkpoint (the rest of its TrainState is not needed)."""
    _, raw = ckpt.read(path, fingerprint)
    restored = serialization.from_state_dict(template, raw["params"])
    return jax.tree.map(lambda t, x: jnp.asarray(x, t.dtype), template, restored)


# ---------------------------------------------------------------------------------------------------
# FCP partner pools
# ---------------------------------------------------------------------------------------------------

def load_pool(config: Config, trainer: ppo.Trainer, partner_run) -> tuple[np.ndarray, list[str]]:
    """Stack the pool of frozen partners from an SP run directory: partner_seeds x checkpoints."""
    fcp = config.population.fcp
    source = RunDir(partner_run)
    if not source.config_path.exists():
        raise RunDirError(f"population.fcp.partners: {partner_run} is not an ocv2 run directory (no config.yaml)")
    partner_config = source.load_config()
    if partner_config.env != config.env or partner_config.model != config.model:
        raise RunDirError(f"population.fcp.partners: {partner_run} was trained with a different env or model "
                          "section; FCP partners must play the same game with the same network")
    if partner_config.population.num_seeds < fcp.partner_seeds:
        raise RunDirError(f"population.fcp.partner_seeds: {fcp.partner_seeds} requested but {partner_run} has "
                          f"{partner_config.population.num_seeds} seeds")
    snapshots = ckpt.snapshot_updates(partner_config.ppo.num_updates, partner_config.run.num_checkpoints)
    template = _params_template(trainer)
    params, labels = [], []
    for seed in range(fcp.partner_seeds):
        for name in fcp.checkpoints:
            update = ckpt.resolve_snapshot(name, snapshots)
            path = ckpt.checkpoint_path(partner_run, seed, update)
            params.append(_load_params(path, partner_config.fingerprint(), template))
            labels.append(f"seed{seed}@{update}")
    return stack_params(params), labels


def _fcp_pool(config: Config, trainer: ppo.Trainer, run: RunDir, show_progress: bool):
    fcp = config.population.fcp
    partner_run = Path(fcp.partners) if fcp.partners else run.path / "partners"
    if fcp.partners is None:
        stage = dataclasses.replace(config, population=dataclasses.replace(
            config.population, method="sp", num_seeds=fcp.partner_seeds, seed=config.population.seed + 7919))
        stage_dir = RunDir(partner_run)
        finished = stage_dir.config_path.exists() and stage_dir.read_manifest().get("status") == "finished"
        if not finished:
            train_population(stage, partner_run, resume=stage_dir.config_path.exists(), show_progress=show_progress,
                             evaluate=False, label="FCP partner stage (SP)")
    return load_pool(config, trainer, partner_run)


# ---------------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------------

def _restore(trainer: ppo.Trainer, run: RunDir, config: Config, seeds: list[int], pool_size: int):
    """The latest update every seed has a checkpoint for, and the stacked states there."""
    common = set.intersection(*(set(ckpt.list_updates(run.path, s)) for s in seeds))
    if not common:
        return None, 0
    update = max(common)
    template = _state_template(trainer, pool_size)
    states = [ckpt.load(ckpt.checkpoint_path(run.path, s, update), template, config.fingerprint())[1] for s in seeds]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states), update


def _save_checkpoints(run: RunDir, config: Config, seeds, states, update: int, schedule: Schedule) -> None:
    host = jax.tree.map(np.asarray, states)
    for index, seed in enumerate(seeds):
        ckpt.save(ckpt.checkpoint_path(run.path, seed, update), ppo.take_seed(host, index), config.fingerprint(),
                  seed=seed, update=update, method=config.population.method)
        # Keep the paper's snapshots and SA iteration starts; older periodic checkpoints are replaced.
        keep = set(schedule.snapshots) | set(schedule.iteration_starts) | {update}
        for old in ckpt.list_updates(run.path, seed):
            if old not in keep:
                ckpt.checkpoint_path(run.path, seed, old).unlink(missing_ok=True)


def _sa_buffer(config: Config, trainer: ppo.Trainer, run: RunDir, states, iteration: int):
    """The iteration's buffer: loaded if this run already collected it (resume), else collected and saved."""
    path = run.path / "sa" / f"buffer_{iteration:03d}.msgpack"
    template = jax.eval_shape(lambda: _collect(config, trainer, states.params, iteration))
    if path.exists():
        return ckpt.load(path, template, config.fingerprint())[1]
    buffer = _collect(config, trainer, states.params, iteration)
    ckpt.save(path, buffer, config.fingerprint(), iteration=iteration, states=int(buffer.step.shape[0]))
    return buffer


def _collect(config: Config, trainer: ppo.Trainer, params, iteration: int):
    key = jax.random.fold_in(jax.random.PRNGKey(config.population.seed), SA_KEY_OFFSET + iteration)
    return collect_buffer(trainer.network.apply, hidden_size(trainer), ppo.eval_env(config), params, key,
                          config.population.sa)


def train_population(config: Config, run_dir, *, resume: bool = False, show_progress: bool = True,
                     evaluate: bool = True, label: str | None = None) -> dict:
    """Train (or resume) a population into ``run_dir``; then cross-play, plots and GIFs. Returns a summary."""
    run = RunDir(run_dir)
    resuming = run.create(config, resume=resume)
    trainer = ppo.make_trainer(config)
    method = config.population.method
    seeds = list(range(config.population.num_seeds))
    schedule = Schedule.of(config)
    pool, pool_labels = None, []
    if method == "fcp":
        pool, pool_labels = _fcp_pool(config, trainer, run, show_progress)
        pool = jax.tree.map(jnp.asarray, pool)
    pool_size = len(pool_labels)
    states, update = _restore(trainer, run, config, seeds, pool_size) if resuming else (None, 0)
    if states is None:
        states = ppo.init_population(trainer, seeds, None, pool_size)
        update = 0
        run.truncate_metrics(0)
        _save_checkpoints(run, config, seeds, states, 0, schedule)
    else:
        run.truncate_metrics(update)
    run.update_manifest(status="training", method=method, num_updates=schedule.num_updates, update=update,
                        snapshots=list(schedule.snapshots), pool=pool_labels, seeds=seeds)
    recipe_labels = ["+".join(map(str, r)) for r in trainer.env.layout.possible_recipes]
    compiled = {}
    buffer = None
    restart = jax.jit(jax.vmap(lambda s, k, b: ppo.restart_episodes(trainer, s, k, b), in_axes=(0, 0, None)))
    progress = PopulationProgress(label or f"{method.upper()} {config.env_kwargs['layout']}", len(seeds),
                                  schedule.num_updates, config.ppo.steps_per_update, enabled=show_progress)
    with progress:
        progress.advance_to(update, None)
        while update < schedule.num_updates:
            if schedule.iteration_starts:
                iteration = schedule.iteration_at(update)
                fresh = update == schedule.iteration_starts[iteration]
                if buffer is None or fresh:
                    progress.note(f"SA iteration {iteration + 1}/{len(schedule.iteration_starts)}: collecting states")
                    buffer = _sa_buffer(config, trainer, run, states, iteration)
                    if fresh:
                        keys = jnp.stack([jax.random.fold_in(ppo.seed_key(config, s), SA_KEY_OFFSET + iteration)
                                          for s in seeds])
                        states = restart(states, keys, buffer)
            stop = schedule.next_stop(update)
            count = stop - update
            if count not in compiled:
                compiled[count] = ppo.make_advance_population(trainer, count)
            started = time.perf_counter()
            states, metrics = compiled[count](states, buffer, pool)
            metrics = jax.tree.map(np.asarray, metrics)
            wall = time.perf_counter() - started
            steps_per_s = len(seeds) * count * config.ppo.steps_per_update / wall
            run.append_metrics(metric_rows(seeds, metrics, steps_per_s, wall, recipe_labels))
            update = stop
            _save_checkpoints(run, config, seeds, states, update, schedule)
            run.update_manifest(update=update)
            progress.advance_to(update, metrics, steps_per_s)
    run.update_manifest(status="trained", update=update)
    summary = {"run_dir": str(run.path), "updates": update}
    if evaluate:
        summary["xp"] = evaluate_run(run.path, show_progress=show_progress)
        summary["plot"] = write_training_plot(run.path)
        summary["gifs"] = write_gifs(run.path, config.eval.gifs)
        summary["archive"] = archive_cross_play(run.path, config.eval.archive_episodes)
    run.update_manifest(status="finished")
    return summary


# ---------------------------------------------------------------------------------------------------
# after training: cross-play, plots, GIFs
# ---------------------------------------------------------------------------------------------------

def final_params(run_dir) -> tuple[Config, ppo.Trainer, object]:
    """Config, trainer and stacked final params of every seed of a finished run."""
    run = RunDir(run_dir)
    if not run.config_path.exists():
        raise RunDirError(f"{run_dir}: not an ocv2 run directory (no config.yaml)")
    config = run.load_config()
    trainer = ppo.make_trainer(config)
    template = _params_template(trainer)
    params = []
    for seed in range(config.population.num_seeds):
        path = ckpt.checkpoint_path(run.path, seed, config.ppo.num_updates)
        if not path.exists():
            raise RunDirError(f"{run_dir}: seed {seed} has not finished training (no {path.name}); "
                              "resume the run first")
        params.append(_load_params(path, config.fingerprint(), template))
    return config, trainer, stack_params(params)


def evaluate_run(run_dir, episodes: int | None = None, show_progress: bool = True) -> dict:
    """Cross-play of the run's final policies -> xp/matrix.csv, episodes.csv, summary.json, heatmap.png."""
    from population.plots import xp_heatmap

    config, trainer, params = final_params(run_dir)
    episodes = episodes or config.eval.episodes
    env = ppo.eval_env(config)
    key = jax.random.fold_in(jax.random.PRNGKey(config.population.seed), XP_KEY_OFFSET)
    started = time.perf_counter()
    result = cross_play(trainer.network.apply, hidden_size(trainer), env, params, key, episodes)
    summary = summarize(result, recipe_names(env))
    summary["wall_s"] = round(time.perf_counter() - started, 2)
    run = RunDir(run_dir)
    num = result.matrix.shape[0]
    write_csv(run.sub("xp", "matrix.csv"), ["seat0\\seat1"] + [f"seed_{j}" for j in range(num)],
               [[f"seed_{i}"] + [round(float(v), 4) for v in result.matrix[i]] for i in range(num)])
    names = recipe_names(env)
    write_csv(run.sub("xp", "episodes.csv"), ["seat0", "seat1", "episode", "return", "start_recipe"],
               [[i, j, e, float(result.returns[i, j, e]), names.get(int(result.start_recipe[i, j, e]), "")]
                for i in range(num) for j in range(num) for e in range(episodes)])
    write_json(run.sub("xp", "summary.json"), summary)
    layout = config.env_kwargs["layout"]
    xp_heatmap(result.matrix, run.sub("xp", "heatmap.png"), title=f"{config.population.method.upper()} {layout}: "
               f"SP {summary['sp_mean']:.1f}, XP {summary['xp_mean']:.1f} ({episodes} episodes/pair)")
    if show_progress:
        print(f"cross-play ({num}x{num}, {episodes} episodes/pair): SP {summary['sp_mean']:.1f} +- "
              f"{summary['sp_std']:.1f}, XP {summary['xp_mean']:.1f} +- {summary['xp_std']:.1f}, "
              f"gap {summary['gap']:.1f}")
    return summary


def write_training_plot(run_dir) -> str | None:
    from population.plots import training_curves

    run = RunDir(run_dir)
    rows = run.read_metrics()
    if not rows:
        return None
    config = run.load_config()
    seeds = sorted({int(r["seed"]) for r in rows})
    updates = sorted({int(r["update"]) for r in rows})
    index = {u: k for k, u in enumerate(updates)}
    curves = {name: np.full((len(seeds), len(updates)), np.nan) for name in ("sparse_return", "shaped_return")}
    for r in rows:
        for name in curves:
            if r[name] != "":
                curves[name][seeds.index(int(r["seed"])), index[int(r["update"])]] = float(r[name])
    steps = np.asarray(updates) * config.ppo.steps_per_update
    return training_curves(steps, curves, run.sub("plots", "training.png"),
                           title=f"{config.population.method.upper()} {config.env_kwargs['layout']} "
                                 f"({len(seeds)} seeds)")


def write_gifs(run_dir, count: int) -> list[str]:
    """Self-play episode GIFs of the first ``count`` seeds' final policies."""
    from ocv2.render import render_frames, write_gif

    if count <= 0:
        return []
    config, trainer, params = final_params(run_dir)
    env = ppo.eval_env(config)
    key = jax.random.fold_in(jax.random.PRNGKey(config.population.seed), GIF_KEY_OFFSET)
    play = jax.jit(lambda p, k: play_episodes(trainer.network.apply, hidden_size(trainer), env, (p, p), k, 1, 1))
    paths = []
    for seed in range(min(count, config.population.num_seeds)):
        episode = play(ppo.take_seed(params, seed), jax.random.fold_in(key, seed))
        states = jax.tree.map(lambda x: x[0], episode.states)
        frames = render_frames(states, env.layout, agent_view_size=env.config.view_radius, tile_size=24)
        path = RunDir(run_dir).sub("gifs", f"seed_{seed}_selfplay.gif")
        paths.append(write_gif(frames, path, fps=8))
    return paths


def archive_cross_play(run_dir, episodes: int) -> str | None:
    """Record ``episodes`` episodes of every ordered pair of final policies to ``archive/xp.mcap``.

    These are fresh episodes (key ``fold_in(xp_key, 1)``), not the ones scored in ``xp/``; every
    state, joint action and reward is kept, so they can be replayed, rendered or used as SA states.
    """
    from cluster.archive import ArchiveWriter, env_meta, record_pairs

    if episodes <= 0:
        return None
    config, trainer, params = final_params(run_dir)
    env = ppo.eval_env(config)
    num = config.population.num_seeds
    key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(config.population.seed), XP_KEY_OFFSET), 1)
    path = RunDir(run_dir).sub("archive", "xp.mcap")
    base = {**env_meta(env), "method": config.population.method, "kind": "cross-play",
            "checkpoint_update": config.ppo.num_updates, "config_fingerprint": config.fingerprint()}
    with ArchiveWriter(path, overwrite=True) as writer:
        for i in range(num):  # one row of pairs per call: at most K parameter copies
            keys = jnp.stack([jax.random.fold_in(key, i * num + j) for j in range(num)])
            metas = [{**base, "policies": [f"seed_{i}", f"seed_{j}"], "seeds": [i, j]} for j in range(num)]
            record_pairs(writer, trainer.network.apply, hidden_size(trainer), env,
                         gather_params(params, [i] * num), params, keys, episodes, metas)
    return str(path)
