"""The Python entry point for population runs: what ``ocv2 train`` does, callable from a script.

    import cluster

    def show(event):
        returns = [row.values["sparse_return"] for row in event.rows]
        print(event.update, "/", event.num_updates, len(event.rows), "new metrics rows, returns", returns)

    summary = cluster.train_population("configs/smoke.yaml", "runs/demo", backend="local",
                                       on_chunk=show, loggers=["tensorboard"])

``on_chunk`` is called after every chunk of updates the coordinator merged (``run.checkpoint_every``)
with a ``ChunkEvent``: the population's update, the run's total, the metrics rows that chunk added to
``metrics.csv`` (``MetricsRow``: seed, update, env_steps and a dict of the other columns; NaN where
nothing was measured) and the run directory. The rows come from the coordinator as it merges them:
the cost of a chunk does not grow with the length of the run. Progress is logged (``logging``) by the
``cluster`` loggers: ``logging.basicConfig(level=logging.INFO)`` shows it in a script. ``loggers`` names experiment loggers fed with the same rows and,
after evaluation, the cross-play summary and heatmap (``cluster.runtime.loggers``).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

from cluster.archive.format import require_mcap
from cluster.runtime import coordinator, ray_backend
from cluster.runtime.local import LocalWorkers
from cluster.runtime.loggers import MetricsLogger, MissingExtraError, check_loggers, make_loggers
from cluster.runtime.rundir import MetricsRow, RunDir
from population.config import Config, load_config
from population.memory import check_fits

BACKENDS = ("ray", "local")


class ChunkEvent(NamedTuple):
    update: int  # updates every seed has finished
    num_updates: int  # updates of the whole run
    rows: list[MetricsRow]  # the metrics.csv rows added since the previous event
    run_dir: Path


def require_backend(backend: str) -> None:
    """A one-line error for an unknown backend, or the Ray backend without Ray installed."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose from {', '.join(BACKENDS)}")
    if backend == "ray":
        try:
            importlib.import_module("ray")
        except ImportError:
            raise MissingExtraError(
                "the Ray backend needs Ray: pip install 'ocv2[ray]', or use --backend local"
            ) from None


def archive_settings(config: Config, evaluate: bool = True) -> list[str]:
    """The settings (``--set`` syntax) that would turn off each part of the trajectory archive this run writes
    or reads; empty when the run needs no archive (and so no ``mcap``)."""
    sa = config.population.traits.resets_from_buffer  # SA's collections and archives
    wanted = {
        "archive.xp=false": evaluate and config.archive.xp,
        "archive.sa_collection=false": sa and config.archive.sa_collection,
        "archive.train_every=0": config.archive.train_every > 0,
        "population.sa.archives=[]": sa and bool(config.population.sa.archives),
    }
    return [setting for setting, used in wanted.items() if used]


def train_population(
    config: Config | str | os.PathLike,
    run_dir,
    *,
    backend: str = "ray",
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    on_chunk: Callable[[ChunkEvent], None] | None = None,
    loggers: Sequence[str] = (),
) -> dict:
    """Train (or resume) a population into ``run_dir``, then (``evaluate``) cross-play, plots, GIFs.

    ``config``: a ``Config`` or a YAML path. ``backend``: "ray" (one actor per shard of seeds; needs
    ``ocv2[ray]``) or "local" (one process). ``loggers``: names from ``cluster.runtime.loggers.LOGGERS``. Returns the
    summary ``ocv2 train`` prints from (run_dir, updates, restarts and, after evaluation, xp).
    Without the ``mcap`` package, a run that writes or reads the trajectory archive (``archive_settings``) is
    an ``ArchiveError`` naming ``pip install mcap`` before anything is written; with it turned off it trains.
    """
    if not isinstance(config, Config):
        config = load_config(config)
    # A run this machine cannot hold is a ConfigError before anything is written (docs/cluster.md, Memory).
    check_fits(config, "local" if backend == "local" else "ray" if config.cluster.address is None else "cluster")
    require_backend(backend)
    check_loggers(loggers)  # before the run directory is touched
    archive_off = archive_settings(config, evaluate)
    if archive_off:  # mcap: a core dependency that an environment set up by hand may lack
        require_mcap(archive_off)
    run_dir = Path(run_dir).resolve()
    # A resumed run retrains the updates after its last checkpoint; the rows an earlier driver already
    # logged up to here are not logged twice (W&B refuses steps that go back). One read, at the start.
    logged = _last_update(run_dir) if resume else 0
    active: list[MetricsLogger] = []
    state = {"started": False}

    def start_loggers() -> None:
        # Once the coordinator has made the run directory: a folder the loggers made first would not
        # be a run directory it may use.
        if not state["started"]:
            state["started"] = True
            active.extend(make_loggers(loggers, run_dir, config))

    def chunk_done(update: int, _workers, new_rows: list[dict]) -> None:
        rows = [row for row in map(MetricsRow.of, new_rows) if row.update > logged]
        start_loggers()
        for logger in active:
            logger.log_rows(rows)
        if on_chunk is not None:
            on_chunk(ChunkEvent(update, config.ppo.num_updates, rows, run_dir))

    try:
        summary = _train(
            config, run_dir, backend, resume=resume, show_progress=show_progress, evaluate=evaluate, on_chunk=chunk_done
        )
        if "xp" in summary:
            start_loggers()
            heatmap = run_dir / "xp" / "heatmap.png"
            for logger in active:
                logger.log_xp(summary["xp"], heatmap if heatmap.is_file() else None)
    finally:
        for logger in active:
            logger.close()
    return summary


def _last_update(run_dir: Path) -> int:
    """The last update in a run's metrics.csv (0 for a run not started yet)."""
    return max((int(float(r["update"])) for r in RunDir(run_dir).read_metrics()), default=0)


def _train(config: Config, run_dir: Path, backend: str, **options) -> dict:
    if backend == "local":
        return coordinator.train(config, run_dir, LocalWorkers, **options)
    return ray_backend.train_population(config, run_dir, **options)
