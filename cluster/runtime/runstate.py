"""What both backends agree on about a run's progress: the schedule of stops and per-seed checkpoints
(save all seeds, then prune; restore the latest readable update common to a set of seeds).

A checkpoint's meta also carries the metrics rows of the chunk that ended there, so a worker that
died after saving but before reporting can still hand the coordinator those rows (no gap in
metrics.csv, no row counted twice).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from population import checkpoints as ckpt
from population import ppo
from population.config import Config, load_config

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Where training must stop: snapshots, SA iteration starts, periodic checkpoints."""

    num_updates: int
    snapshots: tuple[int, ...]
    iteration_starts: tuple[int, ...]  # SA only; () otherwise
    checkpoint_every: int
    protected: tuple[int, ...] = ()  # never pruned: snapshots of the config the run was created with

    @staticmethod
    def of(config: Config, run_dir=None) -> Schedule:
        """``config``'s schedule; with ``run_dir``, the snapshots its ``config.yaml`` names stay protected.

        ``run.num_checkpoints`` may change on ``--resume`` (it is not part of the fingerprint), but FCP
        runs and ``ocv2 play`` find snapshots through the run's own config.yaml: those must survive.
        """
        updates = config.ppo.num_updates
        starts = ()
        if config.population.traits.resets_from_buffer:
            # Laid over the schedule: a truncated run keeps the longer run's iteration starts it reaches.
            iterations, horizon = config.population.sa.iterations, config.ppo.schedule_updates
            starts = {round(i * horizon / iterations) for i in range(iterations)}
            starts = tuple(sorted(s for s in starts if s < updates))
        protected = ()
        if run_dir is not None:
            created = _created_config(run_dir)
            if created is not None:
                protected = tuple(ckpt.snapshot_updates(created.ppo.num_updates, created.run.num_checkpoints))
            protected = tuple(sorted({*protected, *ckpt.earlier_snapshots(run_dir)}))  # an extended run's
        return Schedule(
            updates,
            tuple(ckpt.snapshot_updates(updates, config.run.num_checkpoints)),
            starts,
            config.run.checkpoint_every,
            protected,
        )

    def next_stop(self, update: int) -> int:
        candidates = [b for b in (*self.snapshots, *self.iteration_starts) if b > update]
        candidates.append((update // self.checkpoint_every + 1) * self.checkpoint_every)
        return min(min(candidates), self.num_updates)

    @property
    def longest_chunk(self) -> int:
        """The most updates ``next_stop`` puts between two stops: never past the next multiple of
        ``checkpoint_every``, nor past the last update (at least 1)."""
        return max(1, min(self.checkpoint_every, self.num_updates))

    def iteration_at(self, update: int) -> int:
        return max(i for i, start in enumerate(self.iteration_starts) if start <= update)

    def kept(self, update: int) -> set[int]:
        """Checkpoints to keep once ``update`` is saved: the paper's snapshots, SA iteration starts, the newest."""
        return set(self.snapshots) | set(self.protected) | set(self.iteration_starts) | {update}


def _created_config(run_dir) -> Config | None:
    path = Path(run_dir) / "config.yaml"
    return load_config(path) if path.exists() else None  # None: a shard built outside a run directory


def archive_meta(config: Config, kind: str, **extra) -> dict:
    """Metadata every episode a run archives carries (``record_episodes`` adds the env's own)."""
    return {"method": config.population.method, "kind": kind, **extra, "config_fingerprint": config.fingerprint()}


def pair_meta(seat0: int, seat1: int) -> dict:
    return {"policies": [f"seed_{seat0}", f"seed_{seat1}"], "seeds": [seat0, seat1]}


def hidden_size(trainer: ppo.Trainer) -> int:
    return trainer.network.gru_dim if trainer.network.recurrent else 0


def state_template(trainer: ppo.Trainer, pool_size: int):
    return jax.eval_shape(lambda k: ppo.init_train_state(trainer, k, None, pool_size), jax.random.PRNGKey(0))


def params_template(trainer: ppo.Trainer):
    return state_template(trainer, 1 if trainer.fcp else 0).params


def load_params(path, fingerprint: str, template):
    """Only the network parameters of a seed's checkpoint (the rest of its TrainState is not needed)."""
    _, raw = ckpt.read(path, fingerprint)
    restored = serialization.from_state_dict(template, raw["params"])
    return jax.tree.map(lambda t, x: jnp.asarray(x, t.dtype), template, restored)


def resume_updates(run_dir, seeds) -> list[int]:
    """The updates every seed of ``seeds`` has a checkpoint of, newest first: where a resume of them may start.

    ``save_checkpoints`` writes one seed at a time, so a kill, a full disk or a stopped Ray actor may leave some
    seeds at the stop being saved and the others at the one before, which they all still have: that one comes
    first. [] when no seed has a checkpoint past update 0 (a run stopped before or while saving its first ones:
    starting again from update 0 loses nothing). Seeds with checkpoints past update 0 but none in common (a copy
    or pack missing some seeds' files) raise ``CheckpointError`` naming each seed's updates: starting again
    would prune their checkpoints and cut metrics.csv back, and no common update means none is safe to resume.
    """
    return _common_updates(run_dir, _seed_updates(run_dir, seeds))


def _seed_updates(run_dir, seeds) -> dict[int, list[int]]:
    return {seed: ckpt.list_updates(run_dir, seed) for seed in seeds}


def _common_updates(run_dir, found: dict[int, list[int]]) -> list[int]:
    """``resume_updates`` of the seeds' listed checkpoints ``found``."""
    common = set.intersection(*map(set, found.values())) if found else set()
    if not common and any(update > 0 for updates in found.values() for update in updates):
        listed = "; ".join(f"seed {seed}: {', '.join(map(str, updates)) or 'none'}" for seed, updates in found.items())
        raise ckpt.CheckpointError(
            f"{Path(run_dir) / 'checkpoints'}: the seeds share no checkpoint update ({listed}), so none can resume "
            "them all; put the missing checkpoints back (from the study directory, a copy or a full pack) and resume "
            "again (nothing was trained or deleted)"
        )
    return sorted(common, reverse=True)


def _note_seeds_ahead(run_dir, found: dict[int, list[int]], update: int) -> None:
    """Say so when some seeds (``found``: their checkpoints' updates) have checkpoints past ``update``, the newest
    they all have (a save cut short)."""
    ahead = {seed: updates[-1] for seed, updates in found.items() if updates[-1] > update}
    if ahead:
        listed = ", ".join(f"seed {seed} at {newest}" for seed, newest in ahead.items())
        log.warning(
            "%s: %s, but update %s is the newest every seed of %s has: resuming from it (the updates after it are "
            "trained again, to the same numbers)",
            Path(run_dir) / "checkpoints",
            listed,
            update,
            list(found),
        )


def restore(trainer: ppo.Trainer, run_dir, config: Config, seeds, pool_size: int):
    """(stacked states, update, metrics rows stored with them) at the latest update every seed has
    (``resume_updates``), or None when there is none and the run may start from update 0.

    A damaged checkpoint (truncated, checksum mismatch) falls back to the previous common update, with
    a message; the updates after it are trained again (same numbers: training is deterministic).
    """
    found = _seed_updates(run_dir, seeds)
    common = _common_updates(run_dir, found)
    if not common:
        return None
    _note_seeds_ahead(run_dir, found, common[0])
    template = state_template(trainer, pool_size)

    def at(update):
        loaded = [
            ckpt.load(ckpt.checkpoint_path(run_dir, seed, update), template, config.fingerprint()) for seed in seeds
        ]
        rows = [row for meta, _ in loaded for row in meta.get("metrics", [])]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *[state for _, state in loaded]), update, rows

    for update, older in zip(common, common[1:]):
        try:
            return at(update)
        except ckpt.CorruptCheckpointError as error:
            log.warning("%s; falling back to update %s", error, older)
    try:
        return at(common[-1])
    except ckpt.CorruptCheckpointError as error:
        raise ckpt.CheckpointError(
            f"{error}; no older checkpoint of seeds {list(seeds)} to fall back to: start a new run"
        ) from None


def save_checkpoints(
    run_dir,
    config: Config,
    seeds,
    states,
    update: int,
    schedule: Schedule,
    rows: list[dict] = (),
    merged: int | None = None,
) -> None:
    """Every seed's checkpoint at ``update`` (with its metrics rows), then prune superseded ones.

    All seeds are written before any old file is removed, so a kill at any moment leaves an update
    that every seed of the shard still has. ``merged`` (the coordinator's last merged update) is kept
    too: other shards may not have saved ``update`` yet when a kill comes, and a resume that groups the
    seeds into other shards must still find an update that every seed of each new shard has.
    """
    host = jax.tree.map(np.asarray, states)
    for index, seed in enumerate(seeds):
        seed_rows = [r for r in rows if r["seed"] == seed]
        ckpt.save(
            ckpt.checkpoint_path(run_dir, seed, update),
            ppo.take_seed(host, index),
            config.fingerprint(),
            seed=seed,
            update=update,
            method=config.population.method,
            metrics=seed_rows,
        )
    prune_checkpoints(run_dir, seeds, schedule.kept(update) | ({merged} if merged is not None else set()))


def prune_checkpoints(run_dir, seeds, keep: set[int]) -> None:
    """Remove every checkpoint of ``seeds`` whose update is not in ``keep``."""
    for seed in seeds:
        for old in ckpt.list_updates(run_dir, seed):
            if old not in keep:
                ckpt.checkpoint_path(run_dir, seed, old).unlink(missing_ok=True)
