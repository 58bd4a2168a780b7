"""Atomic, config-checked checkpoints of one seed's ``TrainState``.

Layout: ``<run>/checkpoints/seed_<i>/update_<n>.msgpack``, one sealed file (``population.sealed``):
``{"meta": {...}, "state": <the TrainState state dict>}`` under one SHA-256 over every byte of it, the
metadata included (the metadata carries metric rows that are not in metrics.csv yet, and the update
number a resume continues from). A file is written to a temporary name and renamed, so a reader never
sees half a checkpoint; a file damaged later (disk, copy) is refused instead of restored.
``meta.fingerprint`` is the hash of the training-relevant config; loading into a different config is
refused with a message. Older files still load: version 2 (``{"meta", "state": bytes}`` with
``meta.sha256`` over the state bytes only, so damage to its metadata goes unseen) and version 1 (no
checksum).
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import jax
import numpy as np
from flax import serialization

from ocv2 import boundedjson
from ocv2.atomic import atomic_write
from population.sealed import SealError, is_sealed, seal, unseal

FORMAT_NAME = "ocv2-checkpoint"
FORMAT_VERSION = 3
_NAME = re.compile(r"^update_(\d+)\.msgpack$")
_SEED_DIR = re.compile(r"^seed_([0-9]+)$")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (missing, corrupt, or from another config)."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint whose bytes are damaged (truncated, checksum mismatch): an older one may stand in."""


def seed_dir(run_dir, seed: int) -> Path:
    return Path(run_dir) / "checkpoints" / f"seed_{seed}"


def checkpoint_path(run_dir, seed: int, update: int) -> Path:
    return seed_dir(run_dir, seed) / f"update_{update:07d}.msgpack"


def save(path, state, fingerprint: str, **meta) -> Path:
    """Write ``state`` (a pytree) atomically; extra ``meta`` (JSON-able) is stored beside it."""
    content = {
        "meta": {"version": FORMAT_VERSION, "fingerprint": fingerprint, **meta},
        "state": serialization.to_state_dict(jax.tree.map(np.asarray, state)),
    }
    return atomic_write(Path(path), seal(FORMAT_NAME, FORMAT_VERSION, content))


def read(path, fingerprint: str | None = None) -> tuple[dict, dict]:
    """(meta, raw state dict) of a checkpoint; refuses another config's checkpoint if ``fingerprint``."""
    path = Path(path)
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint") from None
    except Exception as error:  # msgpack raises several types on truncated/corrupt data
        raise CorruptCheckpointError(f"{path}: not a readable ocv2 checkpoint ({error})") from None
    if is_sealed(payload):
        try:
            payload = unseal(payload, FORMAT_NAME, FORMAT_VERSION)
        except SealError as error:
            raise CorruptCheckpointError(f"{path}: {error}") from None
    if not isinstance(payload, dict) or "meta" not in payload or "state" not in payload:
        raise CorruptCheckpointError(f"{path}: not an ocv2 checkpoint (no meta/state)")
    meta, state = payload["meta"], payload["state"]
    if not isinstance(meta, dict):
        raise CorruptCheckpointError(f"{path}: not an ocv2 checkpoint (its meta is a {type(meta).__name__})")
    check_place(path, meta)
    if fingerprint is not None and meta.get("fingerprint") != fingerprint:
        raise CheckpointError(
            f"{path}: checkpoint was written by a different config (fingerprint {meta.get('fingerprint')}, "
            f"this config {fingerprint}); use the run's own config.yaml or a new run directory"
        )
    if isinstance(state, bytes):  # version 2: checksummed state bytes, metadata not covered
        if hashlib.sha256(state).hexdigest() != meta.get("sha256"):
            raise CorruptCheckpointError(f"{path}: checksum mismatch (the file was damaged after it was written)")
        try:
            state = serialization.msgpack_restore(state)
        except Exception as error:
            raise CorruptCheckpointError(f"{path}: not a readable ocv2 checkpoint ({error})") from None
    return meta, state


def check_place(path: Path, meta: dict) -> None:
    """Refuse a checkpoint whose seed or update is not the one its place names (``seed_<i>/update_<n>.msgpack``):
    one copied or renamed by hand would otherwise be exported, cross-played or resumed as that other seed or
    update without a word. A file elsewhere, or one whose metadata does not say, is not checked."""
    named = _NAME.match(path.name)
    placed = {"seed": seed_of_folder(path.parent.name), "update": int(named.group(1)) if named else None}
    wrong = [
        f"{key} {meta[key]} (its place names {where})"
        for key, where in placed.items()
        if where is not None and isinstance(meta.get(key), int) and meta[key] != where
    ]
    if wrong:
        raise CheckpointError(
            f"{path}: holds {' and '.join(wrong)}: a file copied or renamed by hand? Put it back where it was "
            "written, or remove it"
        )


def load(path, template, fingerprint: str | None = None):
    """Restore a checkpoint into the structure of ``template``. Returns (meta, state)."""
    meta, raw = read(path, fingerprint)
    try:
        state = serialization.from_state_dict(template, raw)
    except (KeyError, ValueError, TypeError) as error:
        raise CheckpointError(f"{path}: does not match the expected state structure ({error})") from None
    check_shapes(path, template, state)
    return meta, jax.tree.map(lambda t, x: np.asarray(x, dtype=t.dtype), template, state)


def check_shapes(where, template, tree, error=CheckpointError, what: str = "array") -> None:
    """Raise ``error`` naming ``where`` unless ``tree``'s leaves have ``template``'s count and shapes.

    ``template`` leaves may be arrays or ``jax.ShapeDtypeStruct`` (from ``jax.eval_shape``).
    """
    leaves, restored = jax.tree.leaves(template), jax.tree.leaves(tree)
    if len(leaves) != len(restored):
        raise error(f"{where}: holds {len(restored)} {what}s where {len(leaves)} were expected")
    for t, x in zip(leaves, restored):
        if tuple(t.shape) != np.shape(x):
            raise error(f"{where}: {what} of shape {np.shape(x)} where {tuple(t.shape)} was expected")


def list_updates(run_dir, seed: int) -> list[int]:
    """Update numbers of the seed's checkpoints, ascending."""
    directory = seed_dir(run_dir, seed)
    if not directory.is_dir():
        return []
    found = (_NAME.match(p.name) for p in directory.iterdir())
    return sorted(int(m.group(1)) for m in found if m)


def list_seeds(run_dir) -> list[int]:
    """Seed numbers that have a checkpoint folder (``seed_dir``), ascending."""
    found = (seed_of_folder(folder.name) for folder in (Path(run_dir) / "checkpoints").glob("seed_*"))
    return sorted(seed for seed in found if seed is not None)


def seed_of_folder(name: str) -> int | None:
    """The seed a checkpoint folder's name gives (``seed_<i>``, as ``seed_dir`` makes it); None for any other name."""
    match = _SEED_DIR.match(name)
    return int(match.group(1)) if match else None


def update_of(path) -> int | None:
    """The update of checkpoint file ``path`` (``.../checkpoints/seed_<i>/update_<n>.msgpack``), else None."""
    path = Path(path)
    match = _NAME.match(path.name)
    in_seed_dir = path.parent.name.startswith("seed_") and path.parent.parent.name == "checkpoints"
    return int(match.group(1)) if match and in_seed_dir else None


def latest(run_dir, seed: int) -> Path | None:
    updates = list_updates(run_dir, seed)
    return checkpoint_path(run_dir, seed, updates[-1]) if updates else None


def snapshot_updates(num_updates: int, count: int) -> list[int]:
    """The paper's NUM_CHECKPOINTS snapshots: ``count`` points evenly over [0, num_updates]."""
    return sorted({int(round(x)) for x in np.linspace(0, num_updates, count)})


def earlier_snapshots(run_dir) -> tuple[int, ...]:
    """The snapshots of the earlier stops of an extended run (``cluster.runtime.extend``), which its
    manifest.json records; () for a run never extended. They stay kept like the run's own snapshots."""
    path = Path(run_dir) / "manifest.json"
    try:
        manifest = boundedjson.loads(path.read_text())
    except FileNotFoundError:
        return ()
    except ValueError as error:  # not JSON (UnicodeDecodeError is one too), or nested deeper than any manifest
        raise CheckpointError(f"{path}: is not valid JSON ({error})") from None
    records = manifest_extensions(manifest, path) if isinstance(manifest, dict) else []
    return tuple(sorted({u for record in records for u in record["snapshots"]}))


def manifest_extensions(manifest: dict, path) -> list[dict]:
    """The ``extensions`` records of a run's manifest (``cluster.runtime.extend`` writes one per earlier stop:
    ``from_updates``, ``snapshots``, ...), checked for the keys that decide which checkpoints a run keeps and
    reports: a damaged record would otherwise end a command in a ``TypeError`` or pick the wrong snapshots."""
    records = manifest.get("extensions", [])
    if not isinstance(records, list):
        raise CheckpointError(
            f"{path}: 'extensions' must be a list of records, found {records!r:.80}; restore manifest.json from a copy "
            "(`ocv2 study pack` keeps one) or repair it"
        )
    for i, record in enumerate(records):
        snapshots = record.get("snapshots") if isinstance(record, dict) else None
        if not (
            isinstance(snapshots, list)
            and _is_update(record.get("from_updates"))
            and all(_is_update(u) for u in snapshots)
        ):
            raise CheckpointError(
                f"{path}: extensions[{i}] must be a record with from_updates and snapshots as update numbers "
                f'(integers >= 0), e.g. {{"from_updates": 4, "snapshots": [0, 2, 4], ...}}; found {record!r:.120}; '
                "restore manifest.json from a copy (`ocv2 study pack` keeps one) or repair that record"
            )
    return records


def _is_update(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def run_snapshots(run_dir, num_updates: int, count: int) -> list[int]:
    """The snapshots a run holds: ``snapshot_updates(num_updates, count)``, or for an extended run those of them
    past its last earlier stop plus those before it that were snapshots then. When some of the longer
    schedule's snapshots before that stop were not kept (the two schedules' snapshots do not nest), the
    earlier stops' snapshots stand in for that stretch, so it is still covered."""
    now = snapshot_updates(num_updates, count)
    earlier = earlier_snapshots(run_dir)
    if not earlier:
        return now
    stop = max(earlier)
    kept = {u for u in now if u > stop or u in earlier}
    if len(kept) < len(now):
        kept |= set(earlier)
    return sorted(kept)


def resolve_snapshot(name: str, snapshots: list[int]) -> int:
    """'init' / 'mid' / 'final' / an update number -> an update number among ``snapshots``. 'mid' is the
    middle snapshot (with an even count, the later of the two middle ones)."""
    if name == "init":
        return snapshots[0]
    if name == "final":
        return snapshots[-1]
    if name == "mid":
        return snapshots[len(snapshots) // 2]
    update = int(name)
    if update not in snapshots:
        raise CheckpointError(f"no snapshot at update {update}; snapshots are {snapshots}")
    return update


def pool_updates(names, snapshots: list[int]) -> list[int]:
    """The updates an FCP pool's checkpoint names pick among a partner run's snapshots, one per name.
    ``CheckpointError`` for a name that is no snapshot, or for two names that pick the same update (with two
    snapshots 'mid' is 'final'): the pool would hold one partner twice and the learner would train with fewer
    distinct partners than it asked for, without a word."""
    picked: dict[int, str] = {}
    for name in names:
        update = resolve_snapshot(str(name), snapshots)
        if update in picked:
            raise CheckpointError(
                f"{picked[update]!r} and {str(name)!r} are both update {update} (snapshots {snapshots}): "
                "the pool would hold the same partner twice"
            )
        picked[update] = str(name)
    return list(picked)
