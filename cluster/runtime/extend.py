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

from cluster.runtime.rundir import RunDir, RunDirError, trained_keys_changed
from population import checkpoints as ckpt
from population.config import Config, dump_config

#: What the evaluation at the old stop wrote (its cross-play episodes in ``archive/xp``); kept under
#: ``extended/update_<n>/``: the evaluation at the new stop writes the same paths.
EVALUATION_DIRS = ("xp", "plots", "gifs", "archive/xp")
#: The config keys an extension may change: the stop, and the schedule's length only in how it is written (a
#: run extended to its schedule's end is the whole run, whose config leaves ``schedule_timesteps`` unset).
EXTENDED_KEYS = ("ppo.total_timesteps", "ppo.schedule_timesteps")


def extension_problem(run: Config, now: Config) -> str | None:
    """Why ``run`` (a run's config.yaml) cannot be extended to ``now``; None when it can (or ``now`` is it)."""
    if run.fingerprint() == now.fingerprint():
        return None
    if run.population.traits.partner_pool:
        return "its partners were trained for the old budget; a longer run would need another partner pool"
    changed = [line for line in trained_keys_changed(run, now) if line.split(":")[0] not in EXTENDED_KEYS]
    if changed:
        return "only ppo.total_timesteps may change when a run is extended, but " + "; ".join(changed[:3])
    if run.ppo.schedule_timesteps is None:
        return (
            "it trained its whole schedule (no ppo.schedule_timesteps): training longer would change its "
            "learning-rate schedule, so it is another run"
        )
    if run.ppo.schedule_timesteps != (now.ppo.schedule_timesteps or now.ppo.total_timesteps):
        return (
            f"its schedule is {run.ppo.schedule_timesteps:,} env steps, this config's "
            f"{now.ppo.schedule_timesteps or now.ppo.total_timesteps:,}: that is another run"
        )
    if now.ppo.num_updates < run.ppo.num_updates:
        return f"it trained {run.ppo.num_updates} updates; an extension cannot stop earlier ({now.ppo.num_updates})"
    return None


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
        old_print, new_print = before.fingerprint(), after.fingerprint()
        files = sealed_files(run.path)
        for file in files:  # every file checked before any is written: a refusal leaves the run as it was
            stamp_of(file, old_print, new_print)
        manifest = run.read_manifest()
        old = before.ppo.num_updates
        record = {
            "from_updates": old,
            "to_updates": after.ppo.num_updates,
            "snapshots": ckpt.snapshot_updates(old, before.run.num_checkpoints),
            "fingerprint": old_print,
            "at": time.time(),
        }
        for file in files:
            restamp(file, old_print, new_print)
        kept = run.path / "extended" / f"update_{old:07d}"
        for name in EVALUATION_DIRS:
            source = run.path / name
            if source.exists():
                (kept / name).parent.mkdir(parents=True, exist_ok=True)
                source.rename(kept / name)
        earlier = [r for r in manifest.get("extensions", []) if r.get("fingerprint") != old_print]  # a rerun's
        run.write_manifest({**manifest, "status": "extending", "extensions": [*earlier, record]})
        dump_config(after, run.config_path)  # last: until here the run is still the old one
        return record
    finally:
        run.close()


def sealed_files(run_dir: Path) -> list[Path]:
    """The files of a run that carry its fingerprint: every seed's checkpoints and the SA buffers."""
    run_dir = Path(run_dir)
    return sorted(run_dir.glob("checkpoints/seed_*/update_*.msgpack")) + sorted(run_dir.glob("sa/buffer_*.msgpack"))


def stamp_of(path: Path, old: str, new: str) -> str:
    """The fingerprint ``path`` carries, which must be ``old`` or ``new``; ``RunDirError`` naming the file otherwise
    or when it cannot be read (nothing has been written yet when this is raised)."""
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
    return found


def restamp(path: Path, old: str, new: str) -> None:
    """Rewrite ``path`` (a checkpoint or SA buffer) with fingerprint ``new``; it must carry ``old`` or ``new``."""
    if stamp_of(path, old, new) == new:
        return
    meta, state = ckpt.read(path, old)
    extra = {k: v for k, v in meta.items() if k not in ("version", "fingerprint", "sha256")}
    ckpt.save(path, state, new, **extra)
