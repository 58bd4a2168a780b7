"""A folder of published policies: exported snapshot files and the SHA256SUMS.json that lists them.

    entries = publish_run("runs/sp", "docs/results/my_study/policies", which="snapshots")
    verify("docs/results/my_study/policies", ["sp_seed0_update183.ocv2policy"])   # PolicyError if changed
    listing, problems = folder_problems("docs/results/my_study/policies")        # what ``ocv2 verify`` prints

A study's results carry its populations as ``ocv2 export`` files named ``<run>_seed<i>_update<U>.ocv2policy``,
so a reader can play and cross-play them without the run directory. SHA256SUMS.json lists every file with its
seed, update, env steps per seed and the sha256 of its bytes: scripts that read the files check them against it
first, so a number is only ever recomputed from the files it was computed from. Publishing adds files and never
rewrites one already listed (a published file is a record).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

import jax
import numpy as np

from ocv2 import boundedjson
from ocv2.atomic import atomic_write
from population import checkpoints as ckpt
from population.config import load_run_config
from population.policy import SUFFIX, Policy, PolicyError, env_difference, export_checkpoint, load, same_env

SUMS = "SHA256SUMS.json"
#: Which checkpoints ``publish_run`` exports: the kept snapshots (run.num_checkpoints), only each seed's last
#: checkpoint, or every checkpoint on disk.
WHICH = ("snapshots", "final", "all")


@dataclasses.dataclass(frozen=True)
class PublishedPolicy:
    """One line of SHA256SUMS.json."""

    file: str
    seed: int
    update: int
    env_steps: int | None
    sha256: str

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, entry: dict, where: str = SUMS) -> PublishedPolicy:
        try:
            policy = cls(
                file=str(entry["file"]),
                seed=int(entry["seed"]),
                update=int(entry["update"]),
                env_steps=None if entry.get("env_steps") is None else int(entry["env_steps"]),
                sha256=str(entry["sha256"]),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise PolicyError(f"{where}: entry {entry!r} is not a published policy ({error})") from None
        if Path(policy.file).name != policy.file or policy.file in ("", ".", ".."):
            # A path would check a file outside the folder, which the folder's own files are then never compared to.
            raise PolicyError(f"{where}: entry file {policy.file!r} is not a file name in the listing's folder")
        return policy


def policy_name(run: str, seed: int, update: int) -> str:
    """The published file name of ``run``'s seed ``seed`` at update ``update``."""
    return f"{run}_seed{seed}_update{update}{SUFFIX}"


def sha256_of(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_listing(folder) -> list[PublishedPolicy]:
    """The entries of ``folder``/SHA256SUMS.json (none if the folder has no listing yet)."""
    listed = Path(folder) / SUMS
    if listed.exists() and not listed.is_file():
        raise PolicyError(f"{listed}: a folder, not the listing file")
    if not listed.is_file():
        return []
    try:
        raw = boundedjson.loads(listed.read_text())
    except UnicodeDecodeError as error:
        raise PolicyError(f"{listed}: not UTF-8 text (byte {error.start}: {error.reason})") from None
    except ValueError as error:  # not JSON, or nested deeper than a listing ever is
        raise PolicyError(f"{listed}: not JSON ({error})") from None
    if not isinstance(raw, list):
        raise PolicyError(f"{listed}: a list of entries expected, found {type(raw).__name__}")
    return [PublishedPolicy.from_json(entry, str(listed)) for entry in raw]


def write_listing(folder, entries: Iterable[PublishedPolicy]) -> Path:
    """Write SHA256SUMS.json (sorted by update, seed, file), atomically: a stop leaves the old listing whole."""
    ordered = sorted(entries, key=lambda e: (e.update, e.seed, e.file))
    text = json.dumps([e.to_json() for e in ordered], indent=1) + "\n"
    path = Path(folder) / SUMS
    atomic_write(path, text.encode())
    return path


def publish_checkpoint(run_dir, folder, seed: int, update: int) -> PublishedPolicy:
    """Export ``run_dir``'s seed ``seed`` at update ``update`` into ``folder`` and return its listing entry
    (not yet written into SHA256SUMS.json: ``write_listing`` does that once for many files)."""
    run_dir, folder = Path(run_dir), Path(folder)
    config = load_run_config(run_dir)
    path = folder / policy_name(run_dir.name, seed, update)
    export_checkpoint(run_dir, path, seed=seed, checkpoint=update)
    return PublishedPolicy(path.name, seed, update, update * config.ppo.steps_per_update, sha256_of(path))


def updates_to_publish(run_dir, seed: int, which: str = "snapshots") -> list[int]:
    """The checkpoints of ``seed`` on disk that ``which`` (see ``WHICH``) selects, ascending; never update 0
    (a seed's initial parameters, drawn again from its seed)."""
    if which not in WHICH:
        raise ValueError(f"which={which!r}: expected one of {', '.join(WHICH)}")
    run_dir = Path(run_dir)
    on_disk = [u for u in ckpt.list_updates(run_dir, seed) if u > 0]
    if which == "all" or not on_disk:
        return on_disk
    if which == "final":
        return on_disk[-1:]
    config = load_run_config(run_dir)
    kept = set(ckpt.snapshot_updates(config.ppo.num_updates, config.run.num_checkpoints))
    try:
        kept |= set(ckpt.earlier_snapshots(run_dir))  # an extended run's snapshots from before it was extended
    except ckpt.CheckpointError as error:  # a damaged manifest.json
        raise PolicyError(str(error)) from None
    return [u for u in on_disk if u in kept]


def publish_run(run_dir, folder, which: str = "snapshots") -> list[PublishedPolicy]:
    """Export every seed's checkpoints that ``which`` selects into ``folder`` and list them in its
    SHA256SUMS.json (``publish_runs`` for one run). Returns the entries added."""
    return publish_runs([run_dir], folder, which)[Path(run_dir).name]


def publish_runs(run_dirs, folder, which: str = "snapshots") -> dict[str, list[PublishedPolicy]]:
    """Export every run's checkpoints that ``which`` selects into ``folder`` and list them in its SHA256SUMS.json;
    returns the entries added, per run name. All or nothing:

    - files already listed are left as they are (and checked: a listed file that changed or went missing stops
      it before anything is written);
    - a file of a name to be written that the listing does not know is refused before anything is written
      (publishing never writes over a file);
    - a failure part-way (a damaged checkpoint, a listing that cannot be written, an interrupt) removes every file
      this call wrote, and the folder if this call made it, so no unlisted file is left beside the listed ones;
    - with nothing to add, nothing is written and no folder is made.
    """
    run_dirs, folder = [Path(r) for r in run_dirs], Path(folder)
    listing = checked_listing(folder)
    known = {e.file for e in listing}
    plan = {}
    for run_dir in run_dirs:
        config = load_run_config(run_dir)
        selected = [
            (seed, update)
            for seed in range(config.population.num_seeds)
            for update in updates_to_publish(run_dir, seed, which)
        ]
        for seed, update in selected:
            if policy_name(run_dir.name, seed, update) in known:
                check_same_as_listed(folder, run_dir, seed, update)
        plan[run_dir] = [(s, u) for s, u in selected if policy_name(run_dir.name, s, u) not in known]
    targets: dict[Path, Path] = {}  # file to write -> the run it comes from
    for run_dir, wanted in plan.items():
        for seed, update in wanted:
            path = folder / policy_name(run_dir.name, seed, update)
            if path in targets:
                raise PolicyError(
                    f"{targets[path]} and {run_dir}: both would publish {path.name} (files are named by the run "
                    "directory's name); publish them into separate folders"
                )
            if path.exists() or path.is_symlink():
                raise PolicyError(f"{path}: exists but is not listed in {folder / SUMS}; move it away first")
            targets[path] = run_dir
    added: dict[str, list[PublishedPolicy]] = {run_dir.name: [] for run_dir in run_dirs}
    if not any(plan.values()):
        return added
    made = not folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise PolicyError(f"{folder}: cannot create the policies folder ({error.strerror or error})") from None
    try:
        for run_dir, wanted in plan.items():
            for seed, update in wanted:
                added[run_dir.name].append(publish_checkpoint(run_dir, folder, seed, update))
        write_listing(folder, [*listing, *(entry for entries in added.values() for entry in entries)])
    except BaseException:  # an interrupt too: what is not listed must not stay
        for path in targets:  # none was there before (checked above), so each is this call's, written or not
            path.unlink(missing_ok=True)
        if made and not any(folder.iterdir()):
            folder.rmdir()
        raise
    return added


def check_same_as_listed(folder, run_dir, seed: int, update: int) -> None:
    """The file ``folder`` lists under the name of ``run_dir``'s seed ``seed`` at ``update`` must be that
    checkpoint: files are named by the run directory's name, seed and update only, so a run trained again
    (``--retrain``) or another study's run of the same name would otherwise be taken as published already, and the
    folder would keep the other training's policies without a word. ``PolicyError`` naming the file otherwise."""
    path = Path(folder) / policy_name(Path(run_dir).name, seed, update)
    listed, fresh = load(path), load(run_dir, seed=seed, checkpoint=update)
    same = (listed.model, listed.activation) == (fresh.model, fresh.activation) and _same_arrays(
        listed.params, fresh.params
    )
    if not same:
        raise PolicyError(
            f"{path}: published from another training than {run_dir} seed {seed} at update {update} (its parameters "
            "differ: a run trained again, or another study's run of the same name); publish into a new folder"
        )


def _same_arrays(first, second) -> bool:
    a, b = jax.tree.leaves(first), jax.tree.leaves(second)
    return jax.tree.structure(first) == jax.tree.structure(second) and all(
        np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(a, b, strict=True)
    )


def checked_listing(folder) -> list[PublishedPolicy]:
    """``folder``'s listing, every listed file checked (``verify``): what must hold before more are published
    into it. ``PolicyError`` for a folder that is a file, a bad listing or a changed file."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise PolicyError(f"{folder}: a file, not a policies folder")
    listing = read_listing(folder)
    verify(folder, [e.file for e in listing])
    return listing


def verify(folder, files: Iterable[str | Path]) -> None:
    """Raise ``PolicyError`` naming the first of ``files`` (names or paths in ``folder``) that is not listed in
    its SHA256SUMS.json, is missing, or whose bytes are not the listed ones."""
    folder, files = Path(folder), list(files)
    if files and not (folder / SUMS).is_file():  # say so, rather than "not listed" for a file of a wrong folder
        raise PolicyError(f"{folder}: no {SUMS} (not a published policies folder)")
    listed = {e.file: e.sha256 for e in read_listing(folder)}
    for name in files:
        path = folder / Path(name).name
        if path.name not in listed:
            raise PolicyError(f"{path}: not listed in {folder / SUMS}")
        if problem := _listed_file_problem(path, listed[path.name]):
            raise PolicyError(problem)


def _listed_file_problem(path: Path, sha256: str) -> str | None:
    """What is wrong with a listed file (missing, unreadable, or other bytes than the listed ``sha256``), or None."""
    if not path.is_file():
        return f"{path}: listed in {SUMS} but missing"
    try:
        digest = sha256_of(path)
    except OSError as error:
        return f"{path}: cannot be read ({error.strerror or error})"
    return None if digest == sha256 else _not_published(path, digest, sha256)


def _not_published(path: Path, digest: str, listed: str) -> str:
    """The problem of a file whose bytes (sha256 ``digest``) are not those its folder's listing gives (``listed``)."""
    return (
        f"{path}: not the published file (its sha256 {digest[:12]}... is not the {listed[:12]}... that "
        f"{path.parent / SUMS} lists for it)"
    )


@dataclasses.dataclass(frozen=True)
class FileCheck:
    """What ``check_file`` found for one policy file: the sha256 of its bytes, and the SHA256SUMS.json beside it
    (None where its folder has none) that lists it (``listed``) or not."""

    sha256: str
    listing: Path | None
    listed: bool


def check_file(path) -> FileCheck:
    """The sha256 of a policy file, checked against the SHA256SUMS.json of its folder when there is one (and, for a
    symbolic link, of its target's folder too): a file that a listing names with other bytes (a copy renamed, a file
    changed since it was published) is refused with ``PolicyError`` naming it, so no number is computed from a file
    that only looks like a published one. A listing that cannot be read is refused too, naming it."""
    path = Path(path)
    digest = sha256_of(path)
    checks = [_against_listing(path, digest)]
    if path.is_symlink():
        checks.append(_against_listing(path.resolve(), digest))
    # What to record: a listing that lists the file, else one beside it, else none.
    return max(checks, key=lambda check: (check.listed, check.listing is not None))


def _against_listing(path: Path, digest: str) -> FileCheck:
    listing_path = path.parent / SUMS
    if not listing_path.exists():
        return FileCheck(digest, None, False)
    try:
        listed = {e.file: e.sha256 for e in read_listing(path.parent)}
    except PolicyError as error:
        raise PolicyError(f"{error}; repair it, or move {path.name} out of {path.parent}") from None
    if path.name in listed and listed[path.name] != digest:
        raise PolicyError(_not_published(path, digest, listed[path.name]))
    return FileCheck(digest, listing_path, path.name in listed)


def folder_problems(folder) -> tuple[list[PublishedPolicy], list[str]]:
    """Every problem of a published policies folder, not only the first (what ``ocv2 verify`` reports): listed
    files missing or with other bytes, and policy files the listing does not name (publishing never leaves one).
    Returns the listing and the problems, one line each; ``PolicyError`` where there is no readable listing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PolicyError(f"{folder}: not a folder")
    if not (folder / SUMS).exists():
        raise PolicyError(f"{folder}: no {SUMS} (not a published policies folder)")
    listing = read_listing(folder)
    problems = [p for e in listing if (p := _listed_file_problem(folder / e.file, e.sha256))]
    if not listing:  # publishing writes no listing until it has a file to list
        problems.append(f"{folder / SUMS}: lists no policies")
    known = {e.file for e in listing}
    problems += [f"{p}: not listed in {SUMS}" for p in sorted(folder.glob(f"*{SUFFIX}")) if p.name not in known]
    return listing, problems


def load_population(folder, files: Iterable[str | Path], layout: str | None = None) -> list[Policy]:
    """Load published policies that are to be played as one population (each with itself, or pairs of them):
    every file checked against the folder's SHA256SUMS.json (``verify``), and every policy playing the first one's
    environment with the first one's network, so that one compiled rollout serves them all (and ``layout``, for a
    script that reads a layout's own cells). ``PolicyError`` naming the file and what differs otherwise."""
    folder, files = Path(folder), list(files)
    verify(folder, files)
    policies = [load(folder / Path(name).name) for name in files]
    first = policies[0] if policies else None
    if first is not None and layout is not None and first.env.get("layout") != layout:
        raise PolicyError(
            f"{folder / Path(files[0]).name}: plays layout {first.env.get('layout')!r}; this reads {layout} only"
        )
    for name, policy in zip(files, policies, strict=True):
        where, reference = folder / Path(name).name, Path(files[0]).name
        if not same_env(policy.env, first.env):
            raise PolicyError(
                f"{where}: plays another environment than {reference} ({env_difference(policy.env, first.env)})"
            )
        if (policy.model, policy.activation) != (first.model, first.activation):
            raise PolicyError(f"{where}: plays another network than {reference}")
    return policies
