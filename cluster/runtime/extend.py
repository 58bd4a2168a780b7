"""Extend a truncated run: train on along the same schedule to a later stop.

A truncated run (``ppo.schedule_timesteps`` larger than ``ppo.total_timesteps``) is the first part of the
longer run: its learning-rate schedule, reward-shaping horizon and SA iteration starts are the longer
run's. Raising ``total_timesteps`` (up to the schedule) therefore continues that same run, and the result
is what training straight to the new stop gives (tests compare the two). ``total_timesteps`` is part of
the config fingerprint that guards checkpoints, so extending re-stamps the run's checkpoints and SA buffers
with the new fingerprint (every file is read and checked before the first is rewritten), moves the evaluation
made at the old stop (``xp/``, ``plots/``, ``gifs/``, ``archive/xp/``) to ``extended/update_<n>/``, records the
old stop and its snapshots in the manifest (they stay protected from pruning) and writes the new ``config.yaml``
last. Each file is rewritten atomically and a file already carrying the new fingerprint is left as it is, so an
interrupted extension is finished by running it again.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from cluster.runtime.rundir import RunDir, RunDirError, extension_problem
from population import checkpoints as ckpt
from population.config import Config, dump_config

#: What the evaluation at the old stop wrote (its cross-play episodes in ``archive/xp``); kept under
#: ``extended/update_<n>/``: the evaluation at the new stop writes the same paths.
EVALUATION_DIRS = ("xp", "plots", "gifs", "archive/xp")


def extended_config(run: Config, now: Config) -> Config:
    """The run's own config with ``now``'s stop and schedule: what config.yaml says after the extension. Keys the
    fingerprint does not cover (eval, run, archive, cluster) stay the run's, as on any ``--resume``."""
    ppo = dataclasses.replace(
        run.ppo, total_timesteps=now.ppo.total_timesteps, schedule_timesteps=now.ppo.schedule_timesteps
    )
    return dataclasses.replace(run, ppo=ppo)


def extend_run(path, config: Config) -> dict | None:
    """Make the truncated run in ``path`` a run of ``config`` (a later stop on the same schedule).

    Returns the manifest's record of the extension, or None when the run already has ``config``'s
    fingerprint. Raises ``RunDirError`` naming the run when it cannot be extended (see ``extension_problem``),
    a file of it cannot be read or carries another run's fingerprint (nothing is written then), or another
    process holds it."""
    run = RunDir.existing(path)
    run.lock(advice="wait for it to finish or stop it before extending it")
    try:
        before = run.load_config()
        problem = extension_problem(before, config)
        if problem is not None:
            raise RunDirError(f"{run.path}: cannot be extended to {config.ppo.total_timesteps:,} env steps: {problem}")
        if before.fingerprint() == config.fingerprint():
            return None
        after = extended_config(before, config)
        old_print = before.fingerprint()
        manifest = run.read_manifest()
        old = before.ppo.num_updates
        record = {
            "from_updates": old,
            "to_updates": after.ppo.num_updates,
            "snapshots": ckpt.snapshot_updates(old, before.run.num_checkpoints),
            "fingerprint": old_print,
            "at": time.time(),
        }
        restamp_run(run.path, old_print, after.fingerprint())
        _set_evaluation_aside(run.path, run.path / "extended" / f"update_{old:07d}")
        earlier = [r for r in manifest.get("extensions", []) if r.get("fingerprint") != old_print]  # a rerun's
        run.write_manifest({**manifest, "status": "extending", "extensions": [*earlier, record]})
        dump_config(after, run.config_path)  # last: until here the run is still the old one
        return record
    finally:
        run.close()


def repoint_partners(path, config: Config) -> bool:
    """Make the FCP run in ``path`` take its partners from where ``config`` says, when that is the only thing
    its fingerprint changes: a study directory moved or unpacked elsewhere, its partner run moved with it.
    Where the partners lie is part of the fingerprint, so the run's checkpoints are re-stamped (every file
    checked before the first is rewritten) and ``config.yaml`` is written last, as ``extend_run`` does.

    Returns True when the run was rewritten; False when the partners' place is unchanged or something else
    differs too (resuming then refuses and names it). Raises ``RunDirError`` as ``extend_run``."""
    run = RunDir.existing(path)
    run.lock(advice="wait for it to finish or stop it before resuming it")
    try:
        before = run.load_config()
        fcp = before.population.fcp
        partners = config.population.fcp.partners
        if fcp.partners == partners or None in (fcp.partners, partners):
            return False
        moved = dataclasses.replace(fcp, partners=partners)
        after = dataclasses.replace(before, population=dataclasses.replace(before.population, fcp=moved))
        if after.fingerprint() != config.fingerprint():
            return False
        restamp_run(run.path, before.fingerprint(), after.fingerprint())
        dump_config(after, run.config_path)  # last: until here the run is still the old one
        return True
    finally:
        run.close()


def take_eval_episodes(path, config: Config) -> int | None:
    """Give the run in ``path`` ``config``'s ``eval.episodes`` (a study that now asks for more or fewer cross-play
    episodes per pair): training is untouched (``eval`` is outside the fingerprint), the evaluation made with the
    old count moves to ``reevaluated/episodes_<old>/`` (nothing is deleted) and ``config.yaml`` is written last,
    so the next resume of the finished run evaluates it again. Returns the old count, or None when it is already
    ``config``'s. Raises ``RunDirError`` when another process holds the run."""
    run = RunDir.existing(path)
    run.lock(advice="wait for it to finish or stop it before evaluating it again")
    try:
        before = run.load_config()
        old, new = before.eval.episodes, config.eval.episodes
        if old == new:
            return None
        kept = run.path / "reevaluated" / f"episodes_{old}"
        if kept.exists():  # evaluated at this count before, then at another: the newer set-aside gets its own name
            kept = kept.with_name(f"{kept.name}_{time.strftime('%Y%m%d-%H%M%S')}")
        _set_evaluation_aside(run.path, kept)
        after = dataclasses.replace(before, eval=dataclasses.replace(before.eval, episodes=new))
        dump_config(after, run.config_path)  # last: until here the run keeps its old evaluation settings
        return old
    finally:
        run.close()


def _set_evaluation_aside(run_dir: Path, kept: Path) -> None:
    """Move what the run's evaluation wrote (``EVALUATION_DIRS``, those that exist) under ``kept``, where the next
    evaluation does not write over it."""
    for name in EVALUATION_DIRS:
        source = run_dir / name
        if source.exists():
            (kept / name).parent.mkdir(parents=True, exist_ok=True)
            source.rename(kept / name)


def restamp_run(run_dir: Path, old: str, new: str) -> None:
    """Re-stamp every sealed file of the run with fingerprint ``new``; every file is checked (``check_stamp``) before
    any is written, so a refusal leaves the run as it was."""
    files = sealed_files(run_dir)
    for file in files:
        check_stamp(file, old, new)
    for file in files:
        restamp(file, new)


def sealed_files(run_dir: Path) -> list[Path]:
    """The files of a run that carry its fingerprint: every seed's checkpoints and the SA buffers."""
    run_dir = Path(run_dir)
    return sorted(run_dir.glob("checkpoints/seed_*/update_*.msgpack")) + sorted(run_dir.glob("sa/buffer_*.msgpack"))


def check_stamp(path: Path, old: str, new: str) -> None:
    """``RunDirError`` naming ``path`` unless it can be read and carries fingerprint ``old`` or ``new`` (raised
    before anything has been written)."""
    try:
        meta, _ = ckpt.read(path)
    except ckpt.CheckpointError as error:
        raise RunDirError(
            f"{error}; nothing was changed: restore the file (or remove it, losing that checkpoint) and extend again"
        ) from None
    found = meta.get("fingerprint")
    if found not in (old, new):
        raise RunDirError(
            f"{path}: carries fingerprint {found}, neither the run's ({old}) nor the extension's ({new}); nothing "
            "was changed"
        )


def restamp(path: Path, new: str) -> None:
    """Rewrite ``path`` (a checkpoint or SA buffer, checked by ``check_stamp``) with fingerprint ``new`` unless it
    carries it already."""
    meta, state = ckpt.read(path)
    if meta.get("fingerprint") == new:
        return
    extra = {k: v for k, v in meta.items() if k not in ("version", "fingerprint", "sha256")}
    ckpt.save(path, state, new, **extra)
