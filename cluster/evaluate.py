"""After training: cross-play matrix, training curves, self-play GIFs and the cross-play archive.

``evaluate_run`` and ``archive_cross_play`` spread their K x K pairs over a backend's workers when
given some (one seat-0 row of pairs per job, which keeps every cell's episode keys what they are in
one process: the matrix does not depend on the split); without workers they run here.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from cluster.rundir import RunDir, RunDirError, write_csv, write_json
from cluster.runstate import GIF_KEY_OFFSET, XP_KEY_OFFSET, hidden_size, load_params, params_template, population_key
from population import ppo
from population.config import Config
from population.evaluation import gather_params, play_episodes, stack_params
from population.xp import CrossPlay, cross_play, recipe_names, summarize


def final_params(run_dir) -> tuple[Config, ppo.Trainer, object]:
    """Config, trainer and stacked final params of every seed of a finished run."""
    from population import checkpoints as ckpt

    run = RunDir(run_dir)
    if not run.config_path.exists():
        raise RunDirError(f"{run_dir}: not an ocv2 run directory (no config.yaml)")
    config = run.load_config()
    trainer = ppo.make_trainer(config)
    template = params_template(trainer)
    params = []
    for seed in range(config.population.num_seeds):
        path = ckpt.checkpoint_path(run.path, seed, config.ppo.num_updates)
        if not path.exists():
            raise RunDirError(f"{run_dir}: seed {seed} has not finished training (no {path.name}); "
                              "resume the run first")
        params.append(load_params(path, config.fingerprint(), template))
    return config, trainer, stack_params(params)


def post_training(run_dir, workers=None, show_progress: bool = True) -> dict:
    config = RunDir(run_dir).load_config()
    return {"xp": evaluate_run(run_dir, show_progress=show_progress, workers=workers),
            "plot": write_training_plot(run_dir),
            "gifs": write_gifs(run_dir, config.eval.gifs),
            "archive": archive_cross_play(run_dir, config.eval.archive_episodes, workers=workers)}


def _cross_play_spread(workers, params, key, episodes: int) -> CrossPlay:
    from cluster.coordinator import spread_jobs

    num = jax.tree.leaves(params)[0].shape[0]
    handle = workers.share(jax.tree.map(np.asarray, params))
    returns = np.full((num, num, episodes), np.nan, np.float32)
    recipes = np.zeros((num, num, episodes), np.int32)
    for part in workers.call("cross_play", spread_jobs(workers, list(range(num)),
                                                       lambda rows: (handle, rows, np.asarray(key), episodes))):
        returns[part.rows], recipes[part.rows] = part.returns, part.start_recipe  # by row: idempotent
    if np.isnan(returns).any():
        raise RuntimeError("cross-play: some pairs were not evaluated")
    return CrossPlay(returns, recipes)


def evaluate_run(run_dir, episodes: int | None = None, show_progress: bool = True, workers=None) -> dict:
    """Cross-play of the run's final policies -> xp/matrix.csv, episodes.csv, summary.json, heatmap.png."""
    from population.plots import xp_heatmap

    config, trainer, params = final_params(run_dir)
    episodes = episodes or config.eval.episodes
    env = ppo.eval_env(config)
    key = population_key(config, XP_KEY_OFFSET)
    started = time.perf_counter()
    if workers is None:
        result = cross_play(trainer.network.apply, hidden_size(trainer), env, params, key, episodes)
    else:
        result = _cross_play_spread(workers, params, key, episodes)
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
    key = population_key(config, GIF_KEY_OFFSET)
    play = jax.jit(lambda p, k: play_episodes(trainer.network.apply, hidden_size(trainer), env, (p, p), k, 1, 1))
    paths = []
    for seed in range(min(count, config.population.num_seeds)):
        episode = play(ppo.take_seed(params, seed), jax.random.fold_in(key, seed))
        states = jax.tree.map(lambda x: x[0], episode.states)
        frames = render_frames(states, env.layout, agent_view_size=env.config.view_radius, tile_size=24)
        path = RunDir(run_dir).sub("gifs", f"seed_{seed}_selfplay.gif")
        paths.append(write_gif(frames, path, fps=8))
    return paths


def archive_cross_play(run_dir, episodes: int, workers=None) -> str | None:
    """Record ``episodes`` episodes of every ordered pair of final policies to ``archive/xp.mcap``.

    These are fresh episodes (key ``fold_in(xp_key, 1)``), not the ones scored in ``xp/``; every
    state, joint action and reward is kept, so they can be replayed, rendered or used as SA states.
    Pairs are played row by row (at most K parameter copies at once), spread over ``workers`` if given.
    """
    from cluster.archive import ArchiveWriter, env_meta, record_episodes

    if episodes <= 0:
        return None
    config, trainer, params = final_params(run_dir)
    env = ppo.eval_env(config)
    num = config.population.num_seeds
    key = jax.random.fold_in(population_key(config, XP_KEY_OFFSET), 1)
    rows = []  # (pairs, keys) of each seat-0 row
    for i in range(num):
        rows.append(([(i, j) for j in range(num)], np.stack([np.asarray(jax.random.fold_in(key, i * num + j))
                                                              for j in range(num)])))
    if workers is None:
        from cluster.shard import record_pairs

        recorded = [record_pairs(trainer, env, params, pairs, keys, episodes) for pairs, keys in rows]
    else:
        handle = workers.share(jax.tree.map(np.asarray, params))
        from cluster.coordinator import spread

        blocks = [b for b in spread(list(range(num)), len(workers.shards))]
        jobs = [(s, (handle, [p for i in block for p in rows[i][0]], np.concatenate([rows[i][1] for i in block]),
                     episodes)) for s, block in enumerate(blocks) if block]
        parts = workers.call("record", jobs)
        flat = jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
        recorded = [jax.tree.map(lambda x: x[i * num:(i + 1) * num], flat) for i in range(num)]
    path = RunDir(run_dir).sub("archive", "xp.mcap")
    base = {**env_meta(env), "method": config.population.method, "kind": "cross-play",
            "checkpoint_update": config.ppo.num_updates, "config_fingerprint": config.fingerprint()}
    with ArchiveWriter(path, overwrite=True, foxglove_frames=config.archive.foxglove) as writer:
        for i in range(num):
            for j in range(num):
                record_episodes(writer, env, jax.tree.map(lambda x: x[j], recorded[i]),
                                {**base, "policies": [f"seed_{i}", f"seed_{j}"], "seeds": [i, j]})
    return str(path)
