"""The coordinator: drives a population method over shards of seeds, whatever runs the shards.

Both backends use this loop; they differ only in their ``Workers``: the local backend calls one
in-process ``SeedShard`` holding every seed, the Ray backend one actor per shard (with retries when
an actor dies and is restarted). Per chunk of updates (``run.checkpoint_every``, snapshots and SA
iteration starts are stops too) the coordinator

1. SA, at an iteration start: gathers every shard's params, spreads the all-pairs collection over
   the shards, merges the pair results (keyed by pair, so a retried task cannot count twice), saves
   the buffer to ``sa/buffer_<k>.msgpack`` (a resumed run reloads it) and shares it once;
2. asks every shard to advance to the stop and merges the returned metrics rows keyed by
   (seed, update) into ``metrics.csv``;
3. updates the manifest, the progress view, and (``archive.train_every``) the training archive.

FCP pools come from an SP run directory or an SP stage trained first with the same backend. After
training, cross-play is spread over the shards too (``cluster.runtime.evaluate``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from cluster.archive import ArchiveError, ArchiveReader, ArchiveWriter, record_episodes, states_as_buffer
from cluster.runtime.environment import process_record
from cluster.runtime.evaluate import post_training
from cluster.runtime.interrupt import StoppedAfterChunk
from cluster.runtime.jobs import Workers, WorkersFactory, gather_params, on_every_shard, spread_jobs
from cluster.runtime.progress import PopulationProgress
from cluster.runtime.rundir import RunDir, RunDirError, metric_fields, recipe_labels
from cluster.runtime.runstate import Schedule, archive_meta, load_params, pair_meta, params_template, prune_checkpoints
from cluster.runtime.shard import SABuffer
from population import checkpoints as ckpt
from population import ppo
from population.config import Config
from population.config import shards as seed_shards
from population.evaluation import stack_params
from population.numerics import matmul_precision
from population.policy import network_settings, same_env
from population.published import sha256_of
from population.sa import PairStates, all_pairs, extend_buffer, merge_buffers

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------
# SA buffer
# ---------------------------------------------------------------------------------------------------


def sa_buffer_path(run: RunDir, iteration: int) -> Path:
    return run.path / "sa" / f"buffer_{iteration:03d}.msgpack"


def sa_buffer(config: Config, run: RunDir, workers: Workers, iteration: int, extra=None) -> SABuffer:
    """The iteration's buffer: loaded if this run already collected it (resume), else collected and saved.

    Collection episodes go to ``archive/sa/iteration_<k>.mcap`` first (``archive.sa_collection``);
    the buffer file is written last, so its presence means the iteration is complete. ``extra``:
    states from ``population.sa.archives``, appended to the collected ones.
    """
    path = sa_buffer_path(run, iteration)
    if path.exists():
        meta, _ = ckpt.read(path, config.fingerprint())
        return SABuffer(iteration, ckpt.load(path, buffer_template(config, meta["states"]), config.fingerprint())[1])
    params = workers.share(gather_params(workers))
    num = config.population.num_seeds
    record = config.archive.sa_collection
    results = workers.call(
        "collect", spread_jobs(workers, all_pairs(num), lambda pairs: (params, pairs, iteration, record))
    )
    by_pair = {}
    for result in results:  # keyed by pair: a task that ran twice overwrites its own entry
        for index, pair in enumerate(result.pairs):
            recorded = None if result.recorded is None else jax.tree.map(lambda x: x[index], result.recorded)
            by_pair[tuple(pair)] = (jax.tree.map(lambda x: x[index], result.states), recorded)
    missing = [p for p in all_pairs(num) if p not in by_pair]
    if missing:
        raise RuntimeError(f"SA iteration {iteration}: no states for pairs {missing}")
    if record:
        _archive_collection(config, run, iteration, by_pair)
    pairs = sorted(by_pair)
    buffer = merge_buffers(
        [PairStates(tuple(pairs), jax.tree.map(lambda *xs: np.stack(xs), *[by_pair[p][0] for p in pairs]))]
    )
    buffer = extend_buffer(jax.tree.map(np.asarray, buffer), extra)
    ckpt.save(path, buffer, config.fingerprint(), iteration=iteration, states=int(buffer.step.shape[0]))
    return SABuffer(iteration, buffer)


def archived_states(config: Config):
    """``population.sa.archives`` as one numpy state batch (None without archives). Raises ArchiveError."""
    if not config.population.traits.resets_from_buffer or not config.population.sa.archives:
        return None
    try:
        states = states_as_buffer(
            list(config.population.sa.archives), config.population.sa.keep_every, layout=ppo.eval_env(config).layout
        )
    except ArchiveError as error:
        raise ArchiveError(f"population.sa.archives: {error}") from None
    return jax.tree.map(np.asarray, states)


def pin_archives(config: Config, run: RunDir, resuming: bool) -> None:
    """Record the sha256 of every ``population.sa.archives`` file in the manifest; on a resume, refuse a file
    that changed since (the fingerprint holds their paths, not their bytes, and the SA iterations still to
    come would draw from other states than an uninterrupted run did)."""
    digests = {str(path): sha256_of(Path(path)) for path in config.population.sa.archives}
    kept = run.read_manifest().get("sa_archives") or {}
    for path, digest in digests.items():
        if resuming and kept.get(path) not in (None, digest):
            raise RunDirError(
                f"population.sa.archives: {path} has changed since this run started (sha256 {kept[path][:12]} then, "
                f"{digest[:12]} now), so its later SA iterations would draw from other states; restore the file or "
                "start a new run"
            )
    run.update_manifest(sa_archives=digests)


def _archive_collection(config: Config, run: RunDir, iteration: int, by_pair: dict) -> None:
    env = ppo.eval_env(config)
    base = archive_meta(config, "sa-collection", iteration=iteration)
    path = run.sub("archive", "sa", f"iteration_{iteration:03d}.mcap")
    with ArchiveWriter(path, overwrite=True, foxglove_frames=config.archive.foxglove) as writer:
        for i, j in sorted(by_pair):
            record_episodes(writer, env, by_pair[(i, j)][1], {**base, **pair_meta(i, j)})


def buffer_template(config: Config, size: int):
    """Shapes of a saved buffer of ``size`` states (to load it) without playing anything."""
    one = jax.eval_shape(ppo.eval_env(config).reset_state, jax.random.PRNGKey(0))
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct((size,) + x.shape, x.dtype), one)


# ---------------------------------------------------------------------------------------------------
# FCP partner pools
# ---------------------------------------------------------------------------------------------------


def load_pool(config: Config, trainer: ppo.Trainer, partner_run) -> tuple[object, list]:
    """Stack the frozen partners from an SP run directory: partner_seeds x checkpoints per pool.

    ``population.fcp.pool`` shared: one pool [P, ...] of partner seeds [0, k) and its labels;
    per_seed: a pool per learner [num_seeds, P, ...], learner i's from partner seeds [i*k, (i+1)*k),
    and a list of labels per learner (P = k x checkpoints).
    """
    fcp = config.population.fcp
    partner_config = checked_partner_config(config, partner_run)
    twin = twin_seed_warning(config, partner_config, partner_run)
    if twin:
        log.warning(twin)
    updates = pool_updates(config, partner_config, partner_run)
    template = params_template(trainer)

    def pool_of(seeds) -> tuple[object, list[str]]:
        params, labels = [], []
        for seed in seeds:
            for update in updates:
                path = ckpt.checkpoint_path(partner_run, seed, update)
                params.append(load_params(path, partner_config.fingerprint(), template))
                labels.append(f"seed{seed}@{update}")
        return jax.tree.map(np.asarray, stack_params(params)), labels

    if not fcp.per_seed:
        return pool_of(fcp.pool_seeds(0))
    pools = [pool_of(fcp.pool_seeds(learner)) for learner in range(config.population.num_seeds)]
    return jax.tree.map(lambda *xs: np.stack(xs), *[p for p, _ in pools]), [labels for _, labels in pools]


def same_game_and_network(partner: Config, learner: Config) -> bool:
    """Whether a run of ``partner`` can be an FCP partner of ``learner``: the same game and the same network, its
    activation included (``network_settings``): the learner's network plays the partners' parameters, so a
    partner trained with another activation would be played as a function it never was."""
    return same_env(partner.env_kwargs, learner.env_kwargs) and network_settings(partner) == network_settings(learner)


def checked_partner_config(config: Config, partner_run) -> Config:
    """The partner run's config, checked for what ``load_pool`` will read, without loading a parameter: an ocv2
    run of the same game and network, with enough seeds and each pool checkpoint on disk. ``RunDirError`` naming
    ``population.fcp.partners`` (or ``partner_seeds``) otherwise; ``train`` asks before it makes a run directory."""
    fcp = config.population.fcp
    try:
        partner_config = RunDir.existing(partner_run).load_config()
    except RunDirError as error:
        raise RunDirError(f"population.fcp.partners: {error}") from None
    if not same_game_and_network(partner_config, config):
        raise RunDirError(
            f"population.fcp.partners: {partner_run} was trained with a different env or model "
            "section or ppo.activation; FCP partners must play the same game with the same network"
        )
    needed = fcp.stage_seeds(config.population.num_seeds)
    if partner_config.population.num_seeds < needed:
        per_learner = (
            (
                f" ({config.population.num_seeds} learners x {fcp.partner_seeds}, pool per_seed; "
                "population.fcp.pool=shared needs partner_seeds)"
            )
            if fcp.per_seed
            else ""
        )
        raise RunDirError(
            f"population.fcp.partner_seeds: {needed} partner seeds needed{per_learner} but {partner_run} has "
            f"{partner_config.population.num_seeds} seeds"
        )
    updates = pool_updates(config, partner_config, partner_run)
    for seed in range(needed):
        for name, update in zip(fcp.checkpoints, updates, strict=True):
            path = ckpt.checkpoint_path(partner_run, seed, update)
            if not path.is_file():
                raise RunDirError(
                    f"population.fcp.partners: {path} is missing (the {name} checkpoint of partner seed {seed}); "
                    "is the partner run finished?"
                )
    return partner_config


def pool_updates(config: Config, partner_config: Config, partner_run) -> list[int]:
    """The partner run's updates that ``population.fcp.checkpoints`` names, in order, among the snapshots that
    run keeps (an extended run's earlier stops' too); ``RunDirError`` naming the key otherwise."""
    partner = partner_config.ppo.num_updates, partner_config.run.num_checkpoints
    try:
        snapshots = ckpt.run_snapshots(partner_run, *partner)
    except ckpt.CheckpointError as error:  # a damaged manifest.json of the partner run: not the key's fault
        raise RunDirError(f"the FCP partner run {partner_run}: {error}") from None
    try:
        return ckpt.pool_updates(config.population.fcp.checkpoints, snapshots)
    except ckpt.CheckpointError as error:
        raise RunDirError(f"population.fcp.checkpoints: {partner_run}: {error}") from None


def check_partners(config: Config) -> None:
    """The FCP pool a run will build, checked before anything trains: the partner run a config names
    (``population.fcp.partners``, by ``checked_partner_config``), or else that ``population.fcp.checkpoints``
    picks distinct snapshots the partner stage will keep (``check_stage_pool``). Nothing for a method without a
    partner pool. Not part of parsing, so the run directories of earlier versions still load."""
    fcp = config.population.fcp
    if not config.population.traits.partner_pool:
        return
    if fcp.partners:
        checked_partner_config(config, Path(fcp.partners))
    elif config.population.trains_partners:
        check_stage_pool(config)


def check_stage_pool(config: Config) -> None:
    """The partner stage keeps ``run.num_checkpoints`` snapshots and no other update: a pool checkpoint that is
    none of them would fail only once every partner seed had trained, and two names of one update (``mid`` and
    ``final`` with 2 snapshots) would put each partner in the pool twice. ``RunDirError`` naming the key."""
    stage = partner_stage(config)
    snapshots = ckpt.snapshot_updates(stage.ppo.num_updates, stage.run.num_checkpoints)
    try:
        ckpt.pool_updates(config.population.fcp.checkpoints, snapshots)
    except ckpt.CheckpointError as error:
        raise RunDirError(
            f"population.fcp.checkpoints: {error}; the partner stage keeps run.num_checkpoints="
            f"{stage.run.num_checkpoints} snapshots of its {stage.ppo.num_updates} updates "
            "(population.fcp.partner_ppo.total_timesteps)"
        ) from None


def check_inputs(config: Config) -> None:
    """What a run reads besides its config, checked before anything is trained (``ocv2 validate`` too): the FCP
    partner run (``check_partners``) and the ``population.sa.archives`` files read as training reads them
    (``archived_states``: finished, undamaged, of the run's kitchen). ``RunDirError`` / ``ArchiveError`` naming the
    key."""
    check_partners(config)
    archived_states(config)


def twin_seed_warning(config: Config, partner_config: Config, partner_run) -> str | None:
    """Seed i's initial parameters come from (population.seed, i) alone, so FCP learners trained with
    their partner run's population.seed start as exact copies of the partner seeds of the same index."""
    seed = config.population.seed
    if partner_config.population.seed != seed:
        return None
    return (
        f"population.fcp.partners: {partner_run} was trained with the same population.seed ({seed}), so "
        f"learner i starts from the very parameters of partner seed i; give the FCP run another seed "
        f"(--set population.seed={seed + PARTNER_SEED_OFFSET}) for learners independent of their partners"
    )


#: population.seed of the SP partner stage = the FCP run's seed + this (learners never start as their partners)
PARTNER_SEED_OFFSET = 7919


def partner_stage(config: Config) -> Config:
    """The SP run FCP trains its partners in when ``population.fcp.partners`` is unset.

    Same env and model; ``population.fcp.partner_ppo`` hyperparameters; enough seeds for every pool
    (per_seed: num_seeds x partner_seeds); as many workers as the FCP run itself uses.
    """
    fcp, pop = config.population.fcp, config.population
    seeds = fcp.stage_seeds(pop.num_seeds)
    workers = min(len(seed_shards(config)), seeds)
    return dataclasses.replace(
        config,
        ppo=fcp.partner_ppo,
        population=dataclasses.replace(pop, method="sp", num_seeds=seeds, seed=pop.seed + PARTNER_SEED_OFFSET),
        cluster=dataclasses.replace(config.cluster, workers=workers, seeds_per_actor=1),
    )


def partner_run_of(config: Config, run: RunDir) -> Path:
    """Where an FCP run's partners lie: ``population.fcp.partners``, or its own SP stage in RUN_DIR/partners."""
    fcp = config.population.fcp
    return Path(fcp.partners) if fcp.partners else run.path / "partners"


def fcp_pool(config: Config, run: RunDir, factory: WorkersFactory, show_progress: bool):
    """The FCP pool(s): from ``population.fcp.partners``, or an SP stage trained into RUN_DIR/partners first."""
    fcp = config.population.fcp
    partner_run = partner_run_of(config, run)
    if fcp.partners is None:
        stage = partner_stage(config)
        stage_dir = RunDir(partner_run)
        started = stage_dir.config_path.exists()
        if not (started and stage_dir.read_manifest().get("status") == "finished"):
            train(
                stage,
                partner_run,
                factory,
                resume=started,
                show_progress=show_progress,
                evaluate=False,
                label="FCP partner stage (SP)",
            )
    return load_pool(config, ppo.make_trainer(config), partner_run)


def pool_digests(pool, labels: list) -> dict[str, str]:
    """The sha256 of each partner's parameters in ``pool``, by label (``load_pool``'s pool and labels: [P, ...]
    and a list, or per_seed [learners, P, ...] and a list per learner). Of the parameters, not the checkpoint
    file: re-stamping a partner run (``--extend``, a moved study) rewrites its files, not its partners."""
    leaves = [np.asarray(leaf) for leaf in jax.tree.leaves(pool)]
    if labels and isinstance(labels[0], list):
        places = {label: (i, j) for i, row in enumerate(labels) for j, label in enumerate(row)}
    else:
        places = {label: (j,) for j, label in enumerate(labels)}
    return {label: _arrays_sha256([leaf[place] for leaf in leaves]) for label, place in places.items()}


def _arrays_sha256(arrays) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


#: Manifest states of a run whose every update is trained: a resume then only evaluates it.
TRAINED_STATES = ("trained", "finished")


def pinned_pool(config: Config, run: RunDir, resuming: bool, labels: list, digests: dict) -> dict:
    """The pool record the manifest keeps (``pool``: the labels, ``pool_sha256``: ``pool_digests``), checked on a
    resume against the one the run was started with: where ``fcp_pool`` looks (the partner run's current
    snapshots) can change under a half-trained run, e.g. ``ocv2 train --resume --extend`` on the partner run
    moves its "final" and "mid" and re-stamps the files, which ``load_params`` then accepts. ``RunDirError``
    naming ``population.fcp.partners`` and what changed, before anything trains. A run whose training is
    complete is only evaluated (its pool is used no more): said, and the record of the pool it trained with kept."""
    now = {"pool": labels, "pool_sha256": digests}
    if not resuming:
        return now
    manifest = run.read_manifest()
    then = {"pool": manifest.get("pool"), "pool_sha256": manifest.get("pool_sha256")}
    change = pool_change(then, now)
    if change is None:
        return now
    where = f"population.fcp.partners: {partner_run_of(config, run)}"
    # Every update trained: also when a kill came between the last chunk and the "trained" status, or during a
    # resume that only evaluates (which sets "training" first).
    complete = manifest.get("status") in TRAINED_STATES or (manifest.get("update") or 0) >= config.ppo.num_updates
    if complete:
        log.warning(
            f"{where}: {change} since this run trained against it; its training is complete, so only its "
            "evaluation runs, and the manifest keeps the pool it trained with"
        )
        return {key: value for key, value in then.items() if value is not None}
    raise RunDirError(
        f"{where}: {change} since this run started, so its remaining updates would train against other partners "
        "than the ones it trained with (an `ocv2 train --resume --extend` of the partner run moves its mid and "
        "final snapshots). Put the partner run back as it was or start a new run; nothing was trained"
    )


def pool_change(then: dict, now: dict) -> str | None:
    """What differs between two pool records (``pinned_pool``), or None. A manifest written before the pool's
    sha256 were recorded has only the labels (compared), or, before training started, nothing at all: it is
    taken as it is and the record written on this resume."""
    if then["pool"] is None:
        return None
    if then["pool"] != now["pool"]:
        gone = [label for label in _flat(then["pool"]) if label not in _flat(now["pool"])]
        new = [label for label in _flat(now["pool"]) if label not in _flat(then["pool"])]
        if not gone and not new:
            return "its pool lists the same partners in another order"
        return f"its pool has changed: {_listed(gone)} then, {_listed(new)} now"
    if not then["pool_sha256"]:
        return None
    changed = [label for label, digest in now["pool_sha256"].items() if then["pool_sha256"].get(label) != digest]
    if not changed:
        return None
    shown = ", ".join(
        f"{label} (sha256 {str(then['pool_sha256'].get(label))[:12]} then, {now['pool_sha256'][label][:12]} now)"
        for label in changed[:4]
    )
    more = f" and {len(changed) - 4} more" if len(changed) > 4 else ""
    return f"the parameters of partners {shown}{more} have changed"


def _flat(labels: list) -> list[str]:
    """A pool's labels in one list (per_seed keeps one list per learner)."""
    return [label for item in labels for label in (item if isinstance(item, list) else [item])]


def _listed(labels: list[str]) -> str:
    shown = ", ".join(labels[:6])
    return shown + (f" and {len(labels) - 6} more" if len(labels) > 6 else "") if labels else "none"


# ---------------------------------------------------------------------------------------------------
# the training loop
# ---------------------------------------------------------------------------------------------------


def merge_rows(results, since: int, until: int | None = None) -> list[dict]:
    """Rows of (since, until] from every shard, each (seed, update) once, ordered by seed then update."""
    merged = {}
    for result in results:
        for row in result.rows:
            if since < row["update"] <= (until if until is not None else row["update"]):
                merged[(row["seed"], row["update"])] = row
    return [merged[k] for k in sorted(merged)]


def train(
    config: Config,
    run_dir,
    factory: WorkersFactory,
    *,
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    label: str | None = None,
    on_chunk: Callable | None = None,
) -> dict:
    """Train (or resume) a population into ``run_dir`` with the given backend; then evaluate.

    The run directory stays locked until this returns (a second driver of the same run is refused).
    ``on_chunk(update, workers, rows)`` is called after every merged chunk with the metrics rows it added
    to metrics.csv (on a resume the first call also carries the rows caught up from checkpoints); tests
    use it to kill workers.

    Everything this process traces (in-process shards, evaluation, GIFs) uses ``run.precision``; Ray actors
    set it themselves (``ray_backend._ShardActor``).
    """
    with matmul_precision(config.run.precision):
        extra = archived_states(config)  # a bad archive fails here, before the run directory is touched
        check_partners(config)  # and a bad partner run (check_inputs would read the archives a second time)
        run, resuming = RunDir.open(run_dir, config, resume=resume)
        try:
            return _train_locked(config, run, resuming, factory, show_progress, evaluate, label, on_chunk, extra)
        finally:
            run.close()


def _train_locked(config, run, resuming, factory, show_progress, evaluate, label, on_chunk, extra) -> dict:
    past_events = run.read_manifest().get("restart_events", []) if resuming else []
    if extra is not None:
        pin_archives(config, run, resuming)
    schedule = Schedule.of(config, run.path)
    pool, pool_record = None, {"pool": []}
    if config.population.traits.partner_pool:
        pool, labels = fcp_pool(config, run, factory, show_progress)
        pool_record = pinned_pool(config, run, resuming, labels, pool_digests(pool, labels))
    workers = factory(config, run.path, pool)
    workers.events[:0] = past_events  # restarts of earlier drivers of this run stay on record
    try:
        # Shards restore themselves; the slowest decides where the population stands.
        update = min(workers.call("position", on_every_shard(workers)))
        devices = record_workers(config, run, workers)
        caught_up_rows = resume_metrics(config, run, workers, update)
        run.update_manifest(
            status="training",
            method=config.population.method,
            num_updates=schedule.num_updates,
            update=update,
            snapshots=list(schedule.snapshots),
            **pool_record,
            seeds=list(range(config.population.num_seeds)),
            shards=workers.shards,
            resumed_from=update if resuming else None,
        )
        _train_loop(
            config, run, workers, schedule, update, show_progress, label, on_chunk, extra, caught_up_rows, devices
        )
        summary = {"run_dir": str(run.path), "updates": schedule.num_updates, "restarts": workers.restarts()}
        if evaluate:
            summary.update(post_training(run.path, workers, show_progress=show_progress))
    finally:
        workers.close()
    run.update_manifest(status="finished", restarts=summary["restarts"], restart_events=workers.events)
    return summary


def _train_loop(
    config, run, workers, schedule, update, show_progress, label, on_chunk, extra, unreported, devices
) -> None:
    num_shards = len(workers.shards)
    buffer, buffer_handle = None, None
    progress = PopulationProgress(
        label or f"{config.population.method.upper()} {config.env_kwargs['layout']}",
        config.population.num_seeds,
        schedule.num_updates,
        config.ppo.steps_per_update,
        enabled=show_progress,
        details=devices,
    )
    with progress:
        progress.advance_to(update, None)
        missed = _missed_training_archive(config, run, schedule, update)
        if missed is not None and set(workers.call("position", on_every_shard(workers))) == {update}:
            _archive_training(config, run, workers, missed, update)  # the policies are still those of `update`
        while update < schedule.num_updates:
            if schedule.iteration_starts:
                iteration = schedule.iteration_at(update)
                if buffer is None or buffer.iteration != iteration:
                    # A resume loads what an earlier driver collected: saying "collecting" there misled a reader.
                    doing = "loading its states" if sa_buffer_path(run, iteration).exists() else "collecting states"
                    progress.note(f"SA iteration {iteration + 1}/{len(schedule.iteration_starts)}: {doing}")
                    buffer = sa_buffer(config, run, workers, iteration, extra)
                    buffer_handle = workers.share(buffer)
            stop = schedule.next_stop(update)
            results = workers.call("advance", [(i, (stop, buffer_handle, update)) for i in range(num_shards)])
            # A shard ahead of the others (restored from a later checkpoint than they were) returns its saved
            # rows past this stop too; they are merged at the stops they belong to, once.
            rows = merge_rows(results, update, stop)
            run.append_metrics(rows)
            wall = max(r.wall_s for r in results)
            trained = sum(r.trained_updates * len(workers.shards[i]) for i, r in enumerate(results))
            steps_per_s = trained * config.ppo.steps_per_update / wall if wall > 0 else None
            _archive_training(config, run, workers, update, stop)
            update = stop
            run.update_manifest(update=update, restarts=workers.restarts(), restart_events=workers.events)
            progress.advance_to(update, rows, steps_per_s, restarts=workers.restarts())
            if on_chunk is not None:
                on_chunk(update, workers, [*unreported, *rows])
                unreported = []
            if any(r.stop_requested for r in results):
                raise StoppedAfterChunk  # the first Ctrl-C (cluster.runtime.interrupt), now that the chunk is on disk
    # Every shard has saved the last update: the stop before it, kept for a resume that regroups the seeds, goes.
    prune_checkpoints(run.path, range(config.population.num_seeds), schedule.kept(update))
    run.update_manifest(status="trained", update=update)


def resume_metrics(config: Config, run: RunDir, workers: Workers, update: int) -> list[dict]:
    """Bring ``metrics.csv`` to ``update``, where the shards stand, before training on; returns the rows it
    took from the checkpoints.

    Rows past ``update`` are dropped (they are trained again, identically). A driver killed after the shards
    saved a chunk but before it merged their rows, or a torn last row: those rows live in the checkpoints'
    meta and are collected from the seed whose rows stop earliest. Everything is checked on the file as read
    (``RunDir.metrics_to_resume``, ``check_metrics_cover``) before it is rewritten once, in the run's own
    columns (``metric_fields``), so a refused resume leaves the file as it was.
    """
    fields = metric_fields(recipe_labels(ppo.eval_env(config).layout))
    kept_rows = [r for r in run.metrics_to_resume(fields).rows if int(float(r["update"])) <= update]
    kept = {(int(r["seed"]), int(float(r["update"]))) for r in kept_rows}
    latest = {}
    for seed, row_update in kept:
        latest[seed] = max(latest.get(seed, 0), row_update)
    since = min(latest.get(seed, 0) for seed in range(config.population.num_seeds))
    caught_up_rows = []
    if since < update:
        caught_up = workers.call("advance", [(i, (update, None, since)) for i in range(len(workers.shards))])
        caught_up_rows = [
            row for row in merge_rows(caught_up, since, update) if (int(row["seed"]), int(row["update"])) not in kept
        ]
    check_metrics_cover(run, kept | {(int(r["seed"]), int(r["update"])) for r in caught_up_rows}, update, config)
    run.restart_metrics(fields, kept_rows + caught_up_rows)
    if since < update and any(r.stop_requested for r in caught_up):
        raise StoppedAfterChunk  # a Ctrl-C or SIGTERM during the catch-up: its rows are recorded, now stop
    return caught_up_rows


def check_metrics_cover(run: RunDir, rows: set[tuple[int, int]], update: int, config: Config) -> None:
    """Refuse to train on when metrics.csv lacks rows that no checkpoint can give back (only the last chunk's
    rows travel in a checkpoint's meta): a cut or emptied file would otherwise lose those updates' history for
    good, without a word."""
    missing = {}
    for seed in range(config.population.num_seeds):
        have = {u for s, u in rows if s == seed}
        gone = [u for u in range(1, update + 1) if u not in have]
        if gone:
            missing[seed] = gone
    if missing:
        first = min(min(g) for g in missing.values())
        last = max(max(g) for g in missing.values())
        raise RunDirError(
            f"{run.metrics_path}: lacks the rows of {sum(map(len, missing.values()))} (seed, update) pairs between "
            f"updates {first} and {last} (seeds {sorted(missing)}), and only the last chunk's rows can be rebuilt "
            "from the checkpoints: the file was cut or emptied. Restore it from a copy (`ocv2 study pack` keeps "
            "one) and resume again; nothing was trained"
        )


def describe_workers(workers: Workers) -> list[dict]:
    """Per shard, where it trains (``Workers.describe``; in-process shards without it train here)."""
    describe = getattr(workers, "describe", None)
    if describe is None:
        return [{**process_record(), "worker": "this process", "num_gpus": None} for _ in workers.shards]
    return describe()


def record_workers(config: Config, run: RunDir, workers: Workers) -> list[str]:
    """Ask every worker where it trains, add that to this driver's record in ``environment.json`` with
    ``run.precision`` and ``run.deterministic``, warn about a worker given a GPU it cannot use, and return
    the lines that say it in the run's header."""
    records = [
        {"shard": index, "seeds": list(seeds), **record}
        for index, (seeds, record) in enumerate(zip(workers.shards, describe_workers(workers), strict=True))
    ]
    run.amend_environment(
        run={"precision": config.run.precision, "deterministic": config.run.deterministic}, workers=records
    )
    for record in records:
        gpus, seeds = record.get("num_gpus") or 0, seed_ranges(record["seeds"])
        if gpus > 0 and record["device"] == "cpu":
            log.warning(
                f"seeds {seeds}: their Ray actor was given {gpus:g} GPU (ids {record.get('gpu_ids')}) but JAX trains "
                "on the CPU there: that node's jaxlib has no GPU support (install JAX's CUDA build there, "
                'pip install -U "jax[cuda12]==<the installed jax version>")'
            )
        if config.run.deterministic and record["device"] != "cpu" and not record["xla_gpu_deterministic_ops"]:
            log.warning(
                f"seeds {seeds}: run.deterministic is on but XLA's deterministic GPU ops are not "
                f"(XLA_FLAGS there: {record['xla_flags']!r}); repeated runs may differ"
            )
    groups: dict[tuple, list[dict]] = {}
    for record in records:
        groups.setdefault((record["device"], record["worker"], record.get("num_gpus")), []).append(record)
    if all(record["device"] == "cpu" for record in records):  # the GPU flag may be set, but nothing it governs runs
        determinism = "CPU only, deterministic as it is"
    elif any(record["xla_gpu_deterministic_ops"] for record in records):
        determinism = "XLA's deterministic GPU ops on"
    else:
        determinism = "XLA's deterministic GPU ops off"
    computes = ", ".join(sorted({record["computes"] for record in records}))
    lines = [
        f"run.precision {config.run.precision} (matmuls compute {computes}), "
        f"run.deterministic {str(config.run.deterministic).lower()} ({determinism})"
    ]
    for (device, worker, gpus), members in groups.items():
        seeds = seed_ranges([seed for record in members for seed in record["seeds"]])
        where = worker if worker == "this process" else f"{len(members)} {worker}{'s' * (len(members) > 1)}"
        each = "" if gpus is None else f", {gpus:g} GPU{'s' * (gpus != 1)} each"
        lines.append(f"seeds {seeds} train on {device} ({where}{each})")
    return lines


def seed_ranges(seeds) -> str:
    """``[0, 1, 2, 5]`` -> ``0-2, 5``."""
    parts, seeds = [], sorted(seeds)
    for seed in seeds:
        if parts and seed == parts[-1][1] + 1:
            parts[-1][1] = seed
        else:
            parts.append([seed, seed])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in parts)


def _missed_training_archive(config: Config, run: RunDir, schedule: Schedule, update: int) -> int | None:
    """The stop before ``update`` when the chunk that ended at ``update`` passed a multiple of
    ``archive.train_every`` but its archive is not there (killed after the checkpoints, before the archive was
    written), else None."""
    every = config.archive.train_every
    if not every or update == 0:
        return None
    before = 0
    while (stop := schedule.next_stop(before)) < update:
        before = stop
    if update // every == before // every:
        return None
    path = run.path.joinpath(*_training_archive(update))
    return None if _whole_training_archive(path, config.population.num_seeds) else before


def _whole_training_archive(path, num_seeds: int) -> bool:
    """Whether ``path`` is a finished training archive of one episode per seed. A file ``ocv2 archive recover``
    made of a killed writer's ``.partial`` takes the same name but may hold fewer: written again, not kept."""
    if not path.exists():
        return False
    try:
        reader = ArchiveReader(path)
    except ArchiveError:
        return False
    return reader.finished and not reader.warnings and len(reader) == num_seeds


def _training_archive(update: int) -> tuple[str, ...]:
    """Where the ``archive.train_every`` episodes of ``update`` go, under the run directory."""
    return ("archive", "train", f"update_{update:07d}.mcap")


def _archive_training(config: Config, run: RunDir, workers: Workers, before: int, stop: int) -> None:
    """``archive.train_every``: a self-play episode per seed whenever a multiple of it was passed."""
    every = config.archive.train_every
    if not every or stop // every == before // every:
        return
    env = ppo.eval_env(config)
    results = workers.call("record_selfplay", on_every_shard(workers))
    base = archive_meta(config, "training", checkpoint_update=stop)
    path = run.sub(*_training_archive(stop))
    with ArchiveWriter(path, overwrite=True, foxglove_frames=config.archive.foxglove) as writer:
        for seeds, (_, recorded) in zip(workers.shards, results):
            for index, seed in enumerate(seeds):
                record_episodes(
                    writer, env, jax.tree.map(lambda x: x[index], recorded), {**base, **pair_meta(seed, seed)}
                )
