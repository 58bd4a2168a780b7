"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Every file ocv2 writes whole (checkpoints, configs, CSV/JSON results, plots, GIFs) goes through
``atomic_path``: the content is written to a hidden sibling ``.<stem>.tmp-<pid>-<hex><suffix>``
(same folder, so the rename cannot cross file systems; the suffix kept, so writers that pick a
format from the extension still work), flushed to disk, renamed over the target, and the folder
entry synced. A crash leaves at most a stale temporary, which ``remove_stale_temporaries`` deletes.
A folder written whole (a report, a pack, an unpacked study) is built by ``staged_folder`` beside its place
and moved in at the end.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

TMP_MARK = ".tmp-"


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder: str | os.PathLike) -> None:
    """Make a rename inside ``folder`` durable (a power loss can otherwise undo it while later files survive);
    some file systems refuse to open folders, where the rename itself is all there is."""
    try:
        _fsync_path(Path(folder))
    except OSError:
        pass


@contextmanager
def atomic_path(path: str | os.PathLike, *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write; on a clean exit it replaces ``path``, on an error it is removed.

    ``fsync``: flush the file and its folder entry to disk (survives power loss, not only a killed
    process). Missing parent folders are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}{TMP_MARK}{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        yield tmp
        if fsync:
            _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if fsync:
        fsync_folder(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, fsync: bool = True) -> Path:
    """Write ``data`` (bytes, or text kept byte for byte: no newline translation) atomically."""
    with atomic_path(path, fsync=fsync) as tmp:
        if isinstance(data, str):
            with open(tmp, "w", newline="", encoding="utf-8") as handle:
                handle.write(data)
        else:
            tmp.write_bytes(data)
    return Path(path)


@contextmanager
def staged_folder(path: str | os.PathLike, suffix: str = ".staging", markers: Sequence[str] = ()) -> Iterator[Path]:
    """Yield a new hidden folder beside ``path`` to fill; on a clean exit it takes ``path``'s place whole, on an
    error (any, Ctrl-C included) it is removed and ``path`` is left as it was.

    A folder already at ``path`` (the caller has checked it may go: empty, or an earlier output of its own) is
    moved aside first and removed once the new one is in; if the new one cannot be moved in, it is put back.
    The staging name is unique (``tempfile.mkdtemp``), so no folder of the user's is ever taken for one. An empty
    folder at ``path`` is filled in place instead (staged inside it, the files moved up at the end): it may be one
    that cannot be renamed, such as the current directory (``--out .``) or a mount point. There the move is not one
    step, so ``markers`` -- the names of the files whose presence says the folder is complete (a pack's pack.json,
    a report's report.md) -- are moved last, in the order given, after the others are on disk: a kill part-way never
    leaves a marker without what it vouches for. A failure part-way removes what was moved: the folder is empty again.
    """
    path = Path(path)
    if path.is_dir() and not any(path.iterdir()):
        yield from _staged_inside(path, suffix, markers)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = _new_folder(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        yield staging
        if not path.exists():
            staging.rename(path)
            return
        aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
        try:
            path.rename(aside / path.name)
            staging.rename(path)
        except BaseException:  # a full disk, or Ctrl-C between the two renames
            if not path.exists() and (aside / path.name).exists():
                (aside / path.name).rename(path)  # the earlier folder back where it was
            raise
        finally:
            if path.exists():  # the new folder or the earlier one is in place: what is aside (if anything) may go
                shutil.rmtree(aside, ignore_errors=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # gone already unless something failed


def is_temporary(path: str | os.PathLike) -> bool:
    """Whether ``path`` is one of ``atomic_path``'s temporaries."""
    name = Path(path).name
    return name.startswith(".") and TMP_MARK in name


def remove_stale_temporaries(folder: str | os.PathLike, recursive: bool = True) -> list[Path]:
    """Delete temporaries left by interrupted writes under ``folder``; returns what was removed.

    Call it only where no other process is writing (e.g. with the run directory's lock held).
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    candidates = folder.rglob(f".*{TMP_MARK}*") if recursive else folder.glob(f".*{TMP_MARK}*")
    removed = []
    for path in candidates:
        if path.is_file() and is_temporary(path):
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def _staged_inside(path: Path, suffix: str, markers: Sequence[str]) -> Iterator[Path]:
    staging = _new_folder(prefix=".", suffix=suffix, dir=path)
    moved = []
    try:
        yield staging
        contents, last = _moving_order(staging, markers)
        for group in (contents, last):
            for item in group:
                item.rename(path / item.name)
                moved.append(path / item.name)
            # The renames durable in this order; the files' bytes are not fsynced (a checksum, e.g. pack.json's, tells)
            fsync_folder(path)
    except BaseException:  # Ctrl-C and SIGTERM too: the folder was empty, and must not look half filled
        for item in reversed(moved):  # the markers first
            _remove(item)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _moving_order(staging: Path, markers: Sequence[str]) -> tuple[list[Path], list[Path]]:
    """(what ``staging`` holds other than ``markers``, sorted; the markers it holds, in the order named)."""
    contents = [item for item in sorted(staging.iterdir()) if item.name not in markers]
    last = [staging / name for name in markers if (staging / name).exists()]
    return contents, last


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _new_folder(prefix: str, suffix: str, dir: Path) -> Path:
    """A new uniquely named folder with the permissions ``mkdir`` would give it (``mkdtemp`` makes it 0700, which
    would otherwise become the output's mode once renamed into place)."""
    folder = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=dir))
    mask = os.umask(0)
    os.umask(mask)
    folder.chmod(0o777 & ~mask)
    return folder
