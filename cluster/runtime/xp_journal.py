"""The jobs a cross-play between sources (``ocv2 xp --rows``) has played so far, kept on disk so that a stopped
command continues where it stopped.

A matrix of 10 x 10 policies in both seat orders at 500 episodes a pair is 200 jobs and an hour or more on a laptop;
Ctrl-C, a closed terminal or a killed machine used to lose all of it, because the results are written whole at the
end. Each finished job (one seat-0 policy against one column source, in one seat order) is now saved at once into
``<OUT>.unfinished/`` beside the output folder (on Ray, as each wave of one job per worker returns), with
``request.json``: everything that decides the numbers (each policy's content hash, episodes, episode key, greedy,
seats, precision, environment, the device, a digest of the code and the numeric packages' versions). The same command
finds the folder, checks the request is the same, plays only the jobs not there, and removes the folder once the
results are written. A job's numbers depend on nothing but its own inputs, so a continued matrix is the
uninterrupted one, bit for bit.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np

from cluster.runtime.crossplay import ORDERS
from cluster.runtime.environment import package_versions
from ocv2 import boundedjson
from ocv2.atomic import atomic_path, atomic_write, is_temporary
from population.policy import env_settings

REQUEST = "request.json"
FORMAT = 1
NUMERIC_PACKAGES = ("python", "ocv2", "jax", "jaxlib", "numpy")  # those whose upgrade may change a job's numbers


class JournalMismatch(ValueError):
    """The unfinished folder holds another request's jobs, or damaged ones: continuing would mix two cross-plays."""


def _damaged(folder: Path, path: Path, why: str) -> JournalMismatch:
    return JournalMismatch(f"{path}: damaged ({why}); remove {folder} to start the cross-play again")


def journal_folder(out: str | Path) -> Path:
    """``<OUT>.unfinished`` beside the output folder (``--out .`` included: it names the folder by its full path)."""
    out = Path(out).resolve()
    return out.with_name(f"{out.name}.unfinished")


def request_of(rows, cols, settings: dict, device: str) -> dict:
    """What decides a cross-play's numbers: the policies of ``rows`` and ``cols`` (``PolicyGroup``s) by content, in
    order (a source given by another path is the same), ``settings`` (episodes, seed, greedy, seats, precision and
    ``env``, compared by what it asks for), the ``device`` that plays, and the code that plays it."""
    versions = package_versions()
    return {
        "rows": [list(g.ids) for g in rows],
        "cols": [list(g.ids) for g in cols],
        **settings,
        "env": env_settings(settings["env"]),
        "device": device,
        "code": source_digest(),
        "versions": {name: versions.get(name) for name in NUMERIC_PACKAGES},
    }


def source_digest() -> str:
    """A hash of every Python source of the three packages that play a job (the environment, the learning code and
    this one): an edit to any of them, committed or not, changes it; a commit of docs alone does not. Read from the
    files themselves, so an installed wheel has one too."""
    digest = hashlib.sha256()
    for package in ("ocv2", "population", "cluster"):
        root = Path(importlib.import_module(package).__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root.parent)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def _normalised(request: dict) -> dict:
    """``request`` as it reads back from JSON (tuples as lists), so a saved request compares equal to a new one."""
    return json.loads(json.dumps(request, sort_keys=True, default=str))


class OrderJournal:
    """The jobs of one seat order: ``played()`` as {(group, column group, row in group): (returns, start recipes)},
    and ``record`` for each job as it finishes."""

    def __init__(self, folder: Path, order: str):
        self.folder, self.order = folder, order

    def _path(self, job: tuple[int, int, int]) -> Path:
        return self.folder / f"{self.order}_{job[0]}_{job[1]}_{job[2]}.npz"

    def saved(self) -> list[Path]:
        """The files of this order's finished jobs."""
        return sorted(self.folder.glob(f"{self.order}_*.npz"))

    def played(
        self, shapes: dict[tuple[int, int, int], tuple[int, ...]]
    ) -> dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]]:
        """The saved jobs; ``shapes`` gives every job of this cross-play and the shape of its returns. A file of
        another job, of another shape or that does not read (a disk that filled, an edit by hand) raises
        ``JournalMismatch`` naming it, instead of a traceback or a matrix with holes."""
        done = {}
        name = re.compile(rf"{re.escape(self.order)}_(\d+)_(\d+)_(\d+)\.npz")
        for path in self.saved():
            match = name.fullmatch(path.name)
            job = tuple(int(part) for part in match.groups()) if match else None
            if job not in shapes:
                raise _damaged(self.folder, path, "not the file of one of this cross-play's jobs")
            try:
                with np.load(path) as saved:
                    returns, recipes = saved["returns"], saved["start_recipe"]
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
                raise _damaged(self.folder, path, f"{type(error).__name__}: {error}") from None
            if returns.shape != shapes[job] or recipes.shape != shapes[job]:
                raise _damaged(
                    self.folder, path, f"returns of shape {returns.shape} and {recipes.shape}, not {shapes[job]}"
                )
            done[job] = (returns, recipes)
        return done

    def record(self, job: tuple[int, int, int], returns: np.ndarray, start_recipe: np.ndarray) -> None:
        with atomic_path(self._path(job)) as tmp, open(tmp, "wb") as handle:
            np.savez(handle, returns=returns, start_recipe=start_recipe)


class XPJournal:
    """``<OUT>.unfinished/``: opened (and made) for one request; ``order(name)`` gives each seat order's jobs."""

    def __init__(self, folder: Path, request: dict):
        self.folder, self.request = folder, _normalised({"format": FORMAT, **request})

    @classmethod
    def open(cls, out: str | Path, request: dict) -> XPJournal:
        """The journal of ``request`` for ``out``: a new one, or the unfinished one of the same request.
        ``JournalMismatch`` names what differs when the unfinished one is of another request."""
        journal = cls(journal_folder(out), request)
        saved_path = journal.folder / REQUEST
        if saved_path.is_file():
            try:
                saved = boundedjson.loads(saved_path.read_bytes())
            except (OSError, ValueError) as error:
                raise _damaged(journal.folder, saved_path, f"{type(error).__name__}: {error}") from None
            if not isinstance(saved, dict):
                raise _damaged(journal.folder, saved_path, f"a JSON {type(saved).__name__}, not an object")
            if saved != journal.request:
                raise JournalMismatch(
                    f"{journal.folder} holds the jobs of an unfinished cross-play with other settings (differs in: "
                    f"{_differences(saved, journal.request)}); give the same arguments to continue it, or remove "
                    "that folder to start again"
                )
        elif journal.folder.exists() and any(not is_temporary(p) for p in journal.folder.iterdir()):
            raise JournalMismatch(f"{journal.folder} exists and is no unfinished cross-play ({REQUEST} missing)")
        else:
            made = not journal.folder.exists()
            try:
                atomic_write(saved_path, json.dumps(journal.request, indent=1, sort_keys=True) + "\n")
            except BaseException:
                if made:  # a full disk, say: leave no empty folder behind
                    shutil.rmtree(journal.folder, ignore_errors=True)
                raise
        return journal

    def order(self, name: str) -> OrderJournal:
        return OrderJournal(self.folder, name)

    def count(self) -> int:
        """How many jobs are saved (both seat orders; not a temporary a killed write left, which is hidden)."""
        return sum(len(self.order(name).saved()) for name in ORDERS)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def _differences(saved: dict, new: dict) -> str:
    """The top-level keys whose values differ, each with the saved and the new value when short."""
    parts = []
    for key in sorted(set(saved) | set(new)):
        before, after = saved.get(key), new.get(key)
        if before != after:
            shown = f"{before!r} there, {after!r} now"
            parts.append(f"{key} ({shown})" if len(shown) <= 80 else key)
    return ", ".join(parts)
