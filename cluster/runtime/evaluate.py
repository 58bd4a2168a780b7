"""After training: cross-play matrix (every scored episode archived), training curves, self-play GIFs.

``evaluate_run`` spreads the K x K pairs over a backend's workers when given some (seat-0 rows per
job, which keeps every cell's episode keys what they are in one process: the matrix and the archive
do not depend on the split); without workers it runs here. With ``archive.xp`` (default) every scored
episode is recorded to ``archive/xp/seat0_seed_<i>.mcap``, one file per row, written by whoever
played the row (so no trajectory crosses the object store).
"""

from __future__ import annotations

import logging
import time
from contextlib import ExitStack
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cluster.archive import PARTIAL_SUFFIX, ArchiveWriter, record_episodes
from cluster.runtime.jobs import in_waves
from cluster.runtime.progress import Bar
from cluster.runtime.rundir import RunDir, RunDirError, seed_curves, write_csv, write_json, write_matrix_csv
from cluster.runtime.runstate import archive_meta, hidden_size, load_params, pair_meta, params_template
from ocv2.render import render_frames, write_gif
from population import checkpoints as ckpt
from population import ppo
from population.config import Config
from population.evaluation import play_episodes, stack_params
from population.keys import derive_key
from population.memory import check_crossplay_fits
from population.numerics import matmul_precision
from population.plots import training_curves, xp_heatmap
from population.xp import CrossPlay, cross_play, recipe_names, summarize

log = logging.getLogger(__name__)


def final_params(run_dir) -> tuple[Config, ppo.Trainer, object]:
    """Config, trainer and stacked final params of every seed of a finished run."""
    run = RunDir.existing(run_dir)
    config = run.load_config()
    trainer = ppo.make_trainer(config)
    template = params_template(trainer)
    params = []
    for seed in range(config.population.num_seeds):
        path = ckpt.checkpoint_path(run.path, seed, config.ppo.num_updates)
        if not path.exists():
            raise RunDirError(
                f"{run_dir}: seed {seed} has not finished training (no {path.name}); resume the run first"
            )
        params.append(load_params(path, config.fingerprint(), template))
    return config, trainer, stack_params(params)


def post_training(run_dir, workers=None, show_progress: bool = True) -> dict:
    config = RunDir(run_dir).load_config()
    xp = evaluate_run(run_dir, show_progress=show_progress, workers=workers)
    return {
        "xp": xp,
        "plot": write_training_plot(run_dir),
        "gifs": write_gifs(run_dir, config.eval.gifs),
        "archive": xp.get("archive"),
    }


def play_rows(
    config: Config, trainer: ppo.Trainer, params, rows, key, episodes: int, archive_dir=None, on_progress=None
) -> CrossPlay:
    """Cross-play of seat-0 ``rows``; with ``archive_dir`` every episode also goes to its row's MCAP file.

    ``on_progress(done, total)`` counts blocks of episodes (``population.xp.cross_play``)."""
    env = ppo.eval_env(config)
    apply, hidden = trainer.network.apply, hidden_size(trainer)
    params = jax.tree.map(jnp.asarray, params)
    if archive_dir is None:
        return cross_play(apply, hidden, env, params, jnp.asarray(key), episodes, rows=rows, on_progress=on_progress)
    base = archive_meta(config, "cross-play", scored=True, checkpoint_update=config.ppo.num_updates)
    num = jax.tree.leaves(params)[0].shape[0]
    with ExitStack() as files:
        writers = {
            i: files.enter_context(
                ArchiveWriter(xp_archive_path(archive_dir, i), overwrite=True, foxglove_frames=config.archive.foxglove)
            )
            for i in rows
        }

        def write(row, first, recorded):
            for j in range(num):
                record_episodes(
                    writers[row], env, jax.tree.map(lambda x: x[j], recorded), {**base, **pair_meta(row, j)}, first
                )

        return cross_play(
            apply, hidden, env, params, jnp.asarray(key), episodes, rows=rows, on_block=write, on_progress=on_progress
        )


def xp_archive_path(archive_dir, row: int) -> Path:
    return Path(archive_dir) / f"seat0_seed_{row}.mcap"


def unfinished_xp_archives(archive_dir, num: int) -> list[str]:
    """The ``.partial`` cross-play archives of rows 0..num-1 under ``archive_dir``: an evaluation stopped while it
    wrote them (each holds the episodes written before; ``ocv2 archive recover`` makes a file of them)."""
    paths = (str(xp_archive_path(archive_dir, row)) + PARTIAL_SUFFIX for row in range(num))
    return [path for path in paths if Path(path).is_file()]


def _cross_play_spread(workers, params, key, episodes: int, archive_dir, on_progress=None) -> CrossPlay:
    """Cross-play of every seat-0 row on the workers, in waves of one row per shard, so that ``on_progress(done,
    total)`` (rows) moves while it plays: a local run has one shard, and one job of all rows said nothing for the
    20 minutes a 10 x 10 matrix at 500 episodes takes on 2 cores. A row's numbers do not depend on which job plays
    it (every row uses the same episode keys), so the waves change nothing but when each row is reported."""
    num = jax.tree.leaves(params)[0].shape[0]
    handle = workers.share(jax.tree.map(np.asarray, params))
    directory = None if archive_dir is None else str(archive_dir)
    returns = np.full((num, num, episodes), np.nan, np.float32)
    recipes = np.zeros((num, num, episodes), np.int32)
    if on_progress is not None:
        on_progress(0, num)
    for wave in in_waves(workers, list(range(num))):
        jobs = [(shard, (handle, [row], np.asarray(key), episodes, directory)) for shard, row in wave]
        for part in workers.call("cross_play", jobs):
            returns[part.rows], recipes[part.rows] = part.returns, part.start_recipe  # by row: idempotent
        if on_progress is not None:
            on_progress(len(wave), num)
    if np.isnan(returns).any():
        raise RuntimeError("cross-play: some pairs were not evaluated")
    return CrossPlay(returns, recipes)


def evaluate_run(run_dir, episodes: int | None = None, show_progress: bool = True, workers=None) -> dict:
    """Cross-play of the run's final policies -> xp/matrix.csv, episodes.csv, summary.json, heatmap.png."""
    config, trainer, params = final_params(run_dir)
    key = "eval.episodes" if episodes is None else "episodes"
    episodes = episodes or config.eval.episodes
    num = config.population.num_seeds
    check_crossplay_fits(num, num, episodes, key)
    env = ppo.eval_env(config)
    key = derive_key(config.population.seed, "xp")
    started = time.perf_counter()
    run = RunDir(run_dir)
    archive_dir = run.subdir("archive", "xp") if config.archive.xp else None
    label = f"cross-play {num}x{num}, {episodes} episodes/pair"
    try:
        if workers is None:
            with (
                Bar(label, enabled=show_progress, unit="blocks") as bar,
                matmul_precision(config.run.precision),  # as the run trained (Ray actors set it themselves)
            ):
                result = play_rows(config, trainer, params, range(num), key, episodes, archive_dir, on_progress=bar)
        else:
            with Bar(label, enabled=show_progress, unit="seat-0 rows") as bar:
                result = _cross_play_spread(workers, params, key, episodes, archive_dir, on_progress=bar)
    except BaseException:  # Ctrl-C, a failure: the writers keep what they wrote (docs/archive.md), and say where
        left = unfinished_xp_archives(archive_dir, num) if archive_dir is not None else []
        if left:
            log.warning(
                f"the cross-play stopped before its matrix was written and left {len(left)} unfinished "
                f"archive(s) of the episodes it played: {', '.join(left)}; 'ocv2 xp {run_dir}' plays them again "
                "and replaces them, 'ocv2 archive recover FILE --out OTHER.mcap' keeps these episodes, "
                "or delete them"
            )
        raise
    summary = summarize(result, recipe_names(env))
    summary["wall_s"] = round(time.perf_counter() - started, 2)
    if archive_dir is not None:
        summary["archive"] = str(archive_dir)
    num = result.matrix.shape[0]
    labels = [f"seed_{i}" for i in range(num)]
    write_matrix_csv(run.sub("xp", "matrix.csv"), result.matrix, labels, labels)
    names = recipe_names(env)
    write_csv(
        run.sub("xp", "episodes.csv"),
        ["seat0", "seat1", "episode", "return", "start_recipe"],
        [
            [i, j, e, float(result.returns[i, j, e]), names.get(int(result.start_recipe[i, j, e]), "")]
            for i in range(num)
            for j in range(num)
            for e in range(episodes)
        ],
    )
    write_json(run.sub("xp", "summary.json"), summary)
    layout = config.env_kwargs["layout"]
    xp_heatmap(
        result.matrix,
        run.sub("xp", "heatmap.png"),
        title=f"{config.population.method.upper()} {layout}: "
        f"SP {summary['sp_mean']:.1f}, XP {summary['xp_mean']:.1f} ({episodes} episodes/pair)",
    )
    if show_progress:
        log.info(
            f"cross-play ({num}x{num}, {episodes} episodes/pair): SP {summary['sp_mean']:.1f} +- "
            f"{summary['sp_std']:.1f}, XP {summary['xp_mean']:.1f} +- {summary['xp_std']:.1f}, "
            f"gap {summary['gap']:.1f}"
        )
    return summary


def write_training_plot(run_dir) -> str | None:
    run = RunDir(run_dir)
    rows = run.read_metrics()
    if not rows:
        return None
    config = run.load_config()
    curves = seed_curves(rows, ("sparse_return", "shaped_return"))
    steps = np.asarray(curves.updates) * config.ppo.steps_per_update
    return training_curves(
        steps,
        curves.values,
        run.sub("plots", "training.png"),
        title=f"{config.population.method.upper()} {config.env_kwargs['layout']} ({len(curves.seeds)} seeds)",
    )


def write_gifs(run_dir, count: int) -> list[str]:
    """Self-play episode GIFs of the first ``count`` seeds' final policies."""
    if count <= 0:
        return []
    config, trainer, params = final_params(run_dir)
    env = ppo.eval_env(config)
    play = jax.jit(lambda p, k: play_episodes(trainer.network.apply, hidden_size(trainer), env, (p, p), k, 1, 1))
    paths = []
    for seed in range(min(count, config.population.num_seeds)):
        with matmul_precision(config.run.precision):
            episode = play(ppo.take_seed(params, seed), derive_key(config.population.seed, "gif", member=seed))
        states = jax.tree.map(lambda x: x[0], episode.states)
        frames = render_frames(states, env.layout, agent_view_size=env.config.view_radius, tile_size=24)
        path = RunDir(run_dir).sub("gifs", f"seed_{seed}_selfplay.gif")
        paths.append(write_gif(frames, path, fps=8))
    return paths
