"""A shard of a population's seeds: the plain class both backends train with.

The local backend runs one shard holding every seed; the Ray backend wraps the same class in an
actor per shard (``cluster.runtime.ray_backend``). A shard restores itself from the run directory's
checkpoints when constructed, which is what makes a restarted Ray actor resume where it left off.

Every method is idempotent with respect to what the coordinator asked for: ``advance(target)`` trains
only what is missing up to ``target`` and returns the metrics rows the coordinator has not merged yet
(recovered from checkpoint meta if the shard had saved them before dying), ``collect``/``cross_play``
depend only on their arguments.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cluster.runtime.evaluate import play_rows
from cluster.runtime.interrupt import ChunkWait
from cluster.runtime.rundir import metric_rows, recipe_labels
from cluster.runtime.runstate import Schedule, hidden_size, restore, save_checkpoints
from population import ppo
from population.config import Config
from population.evaluation import gather_params
from population.keys import derive_key
from population.record import jitted_play_recorded_pairs
from population.sa import collect_pairs


class SABuffer(NamedTuple):
    """The reset buffer of one SA iteration (numpy ``State`` [B, ...]), tagged so shards can cache it."""

    iteration: int
    states: object


class AdvanceResult(NamedTuple):
    update: int  # where the shard now stands
    rows: list  # metrics.csv rows of updates in (since, update]
    trained_updates: int  # updates actually computed by this call (0 if it only reported)
    wall_s: float
    stop_requested: bool = False  # Ctrl-C or SIGTERM during the chunk: stop once it is recorded


class CollectResult(NamedTuple):
    pairs: list  # [(i, j), ...]
    states: object  # numpy State [len(pairs), R * S, ...]: the kept states of each pair
    recorded: object  # numpy population.record.Recorded [len(pairs), R, ...] or None


class CrossPlayRows(NamedTuple):
    rows: list  # seat-0 policy indices
    returns: np.ndarray  # [len(rows), K, E]
    start_recipe: np.ndarray  # [len(rows), K, E]


def record_pairs(trainer: ppo.Trainer, env, params, pairs, keys, episodes: int):
    """``pairs`` of the K stacked ``params`` play ``episodes`` each with every transition kept (numpy)."""
    params = jax.tree.map(jnp.asarray, params)
    play = jitted_play_recorded_pairs(trainer.network.apply, hidden_size(trainer), env, episodes)
    recorded = play(
        gather_params(params, [p[0] for p in pairs]), gather_params(params, [p[1] for p in pairs]), jnp.asarray(keys)
    )
    return jax.tree.map(np.asarray, recorded)


class SeedShard:
    """Train, collect and evaluate for the seeds ``seeds`` of the run in ``run_dir``.

    Args:
        config: the run's config.
        run_dir: the run directory (an existing one: the coordinator creates it).
        seeds: this shard's seed indices.
        pool: FCP only, the stacked frozen partner params (numpy or jax): one pool [P, ...] shared by
            all seeds, or with ``population.fcp.pool: per_seed`` one per seed of the run [num_seeds, P, ...]
            (the shard keeps its own seeds' rows).
    """

    def __init__(self, config: Config, run_dir, seeds: Sequence[int], pool=None):
        self.config, self.run_dir, self.seeds = config, str(run_dir), [int(s) for s in seeds]
        self.trainer = ppo.make_trainer(config)
        self.schedule = Schedule.of(config, run_dir)
        self.pool_per_seed = config.population.fcp.per_seed
        self.pool = None if pool is None else jax.tree.map(jnp.asarray, self._own_pool(pool))
        pool_size = 0 if pool is None else int(jax.tree.leaves(self.pool)[0].shape[int(self.pool_per_seed)])
        restored = restore(self.trainer, self.run_dir, config, self.seeds, pool_size)
        if restored is None:  # no seed past update 0; seeds that share no update were refused, not started over
            self.states, self.update, self._saved_rows = (
                ppo.init_population(self.trainer, self.seeds, None, pool_size),
                0,
                [],
            )
            save_checkpoints(self.run_dir, config, self.seeds, self.states, 0, self.schedule)
        else:
            self.states, self.update, self._saved_rows = restored
        self.restored_update = self.update
        self._restarted_iteration = None  # SA: the iteration whose episode restart self.states has had
        self._buffer = None  # SA: (iteration, jnp State) converted once per iteration
        # One training program per shard (per config in a process: ppo caches it), built at the first chunk.
        # Chunks end at checkpoints, snapshots and SA iteration starts, so their lengths vary (1 to 50 updates
        # in a Coordination Ring SA run); the length is a traced argument of the program
        # (``ppo.make_advance_chunks``), not a constant compiled into it, so every chunk reuses one executable.
        # Stops on a common grid would need no traced count, but the grid of those stops is their greatest
        # common divisor (often 1 update): a host round trip per update, or checkpoints and SA iterations
        # moved off the config's updates.
        self._advance = None
        self._restart = ppo.make_restart_population(self.trainer)
        env = self.trainer.env
        self._recipe_labels = recipe_labels(env.layout)  # the columns the run directory checks on resume

    def _own_pool(self, pool):
        """FCP per_seed: the pools of this shard's seeds (``pool`` holds one per learner of the run)."""
        if not self.pool_per_seed:
            return pool
        learners = int(jax.tree.leaves(pool)[0].shape[0])
        if learners != self.config.population.num_seeds:
            raise ValueError(
                f"FCP per_seed pool has {learners} learner pools for {self.config.population.num_seeds} seeds"
            )
        return jax.tree.map(lambda x: np.asarray(x)[self.seeds], pool)

    # -- training
    def position(self) -> int:
        return self.update

    def advance(self, target: int, buffer: SABuffer | None = None, since: int | None = None) -> AdvanceResult:
        """Train up to update ``target`` (a stop of the schedule), checkpointing at every stop.

        ``since``: the coordinator's last merged update; rows after it that this shard saved before a
        restart are returned too.
        """
        since = self.update if since is None else since
        rows = [r for r in self._saved_rows if since < r["update"] <= self.update]
        started, trained = time.perf_counter(), 0
        while self.update < target:
            self._start_iteration(buffer)
            stop = self.schedule.next_stop(self.update)
            count = stop - self.update
            longest = self.schedule.longest_chunk
            if count > longest:  # the program's metrics buffer holds `longest` rows; it cannot say so itself
                raise RuntimeError(f"chunk of {count} updates from update {self.update}: more than {longest}")
            if self._advance is None:
                self._advance = ppo.make_advance_chunks(self.trainer, longest, self.pool_per_seed)
            chunk_start = time.perf_counter()
            wait = ChunkWait(f"updates {self.update + 1}-{stop}", f"resuming continues from update {self.update}")
            self.states, metrics = wait.until_ready(
                self._advance(self.states, self._device_buffer(buffer), self.pool, np.int32(count))
            )
            metrics = jax.tree.map(lambda x: np.asarray(x)[:, :count], metrics)  # rows past count: padding
            wall = time.perf_counter() - chunk_start
            steps_per_s = len(self.seeds) * count * self.config.ppo.steps_per_update / wall
            chunk_rows = metric_rows(self.seeds, metrics, steps_per_s, wall, self._recipe_labels)
            save_checkpoints(
                self.run_dir, self.config, self.seeds, self.states, stop, self.schedule, chunk_rows, merged=since
            )
            self.update, self._saved_rows = stop, chunk_rows
            rows += chunk_rows
            trained += count
            if wait.stop_requested:  # Ctrl-C: this chunk is saved; the coordinator records it, then stops
                return AdvanceResult(self.update, rows, trained, time.perf_counter() - started, stop_requested=True)
        return AdvanceResult(self.update, rows, trained, time.perf_counter() - started)

    def _start_iteration(self, buffer: SABuffer | None) -> None:
        """SA: at an iteration's first update every environment restarts from the new buffer."""
        starts = self.schedule.iteration_starts
        if not starts:
            return
        iteration = self.schedule.iteration_at(self.update)
        if buffer is None or buffer.iteration != iteration:
            raise ValueError(
                f"SA shard at update {self.update} needs the buffer of iteration {iteration}, got "
                f"{None if buffer is None else buffer.iteration}"
            )
        if self.update == starts[iteration] and self._restarted_iteration != iteration:
            keys = jnp.stack(
                [derive_key(self.config.population.seed, "sa_restart", iteration, member=s) for s in self.seeds]
            )
            self.states = self._restart(self.states, keys, self._device_buffer(buffer))
        self._restarted_iteration = iteration

    def _device_buffer(self, buffer: SABuffer | None):
        if buffer is None:
            return None
        if self._buffer is None or self._buffer[0] != buffer.iteration:
            # Arrays from Ray's object store are read-only views; jnp.asarray copies them once.
            self._buffer = (buffer.iteration, jax.tree.map(jnp.asarray, buffer.states))
        return self._buffer[1]

    def params(self):
        """This shard's current params, stacked [len(seeds)], as numpy (cheap to ship between processes)."""
        return jax.tree.map(np.asarray, self.states.params)

    # -- population-wide work handed out by the coordinator
    def collect(self, params, pairs, iteration: int, record: bool) -> CollectResult:
        """SA collection for ``pairs`` of the K stacked ``params``; with ``record``, the full episodes too."""
        key = derive_key(self.config.population.seed, "sa", iteration)
        env = ppo.eval_env(self.config)
        params = jax.tree.map(jnp.asarray, params)
        part, recorded = collect_pairs(
            self.trainer.network.apply,
            hidden_size(self.trainer),
            env,
            params,
            key,
            self.config.population.sa,
            pairs,
            record=record,
        )
        return CollectResult(
            [tuple(p) for p in part.pairs],
            jax.tree.map(np.asarray, part.states),
            None if recorded is None else jax.tree.map(np.asarray, recorded),
        )

    def cross_play(self, params, rows, key, episodes: int, archive_dir=None) -> CrossPlayRows:
        """Cross-play of seat-0 ``rows``; with ``archive_dir`` their episodes are archived there, one file per row."""
        result = play_rows(self.config, self.trainer, params, rows, key, episodes, archive_dir)
        rows = list(rows)
        return CrossPlayRows(rows, result.returns[rows], result.start_recipe[rows])

    def record_selfplay(self):
        """One self-play episode per seed of the current policies (``archive.train_every``)."""
        keys = np.stack(
            [
                np.asarray(derive_key(self.config.population.seed, "train_archive", self.update, member=s))
                for s in self.seeds
            ]
        )
        local = [(i, i) for i in range(len(self.seeds))]
        return self.update, record_pairs(self.trainer, ppo.eval_env(self.config), self.params(), local, keys, 1)

    def ping(self) -> int:
        return os.getpid()
