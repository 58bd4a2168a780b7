"""A study directory as a few bounded files, and back: how a study crosses from one short machine loan to the next.

A lent GPU machine returns at most 8 files of 16 MiB and takes at most 64 MiB along (work tree included),
and the machine that ran a study may be gone by the next session. ``pack_study`` writes what resuming
needs -- study.json, each run's config.yaml, metrics.csv, manifests and results, and its kept checkpoints
-- as one gzipped tar cut into parts of at most ``part_bytes``, plus ``pack.json`` naming the study, the
parts and their sha256. Left out, because they are pictures or logs made again from the rest or not needed
to go on: GIFs, plots, MCAP archives, ``*.png`` and the directory lock. ``unpack_study`` checks every part's
sum before writing anything, then unpacks into a directory that must not exist yet (a half-unpacked study
would look resumable); ``ocv2 study run`` with the same study file then continues it to the same numbers as
an uninterrupted run (training does not depend on where it was interrupted).

    ocv2 study pack studies/cr --out packed/      # packed/pack.json, packed/study.tar.gz.000, ...
    ocv2 study unpack packed/ --out studies/cr
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cluster.runtime.rundir import LOCK_NAME, DirLock, RunDir, RunDirError
from cluster.runtime.runstate import resume_updates
from cluster.study.runner import Step, check_folder, kept_study, missing_runs, read_state, run_finished
from cluster.study.spec import RESERVED_NAMES, Study, StudyError, run_dir
from cluster.study.state import StepRecord, StudyState
from ocv2 import boundedjson
from ocv2.atomic import staged_folder
from population import checkpoints as ckpt

PACK_NAME = "pack.json"
PART_BYTES = 15 << 20  # a MiB under the largest file the device tool brings back (16 MiB): no part sits at its limit
_SKIPPED_DIRS = set(RESERVED_NAMES)  # which is why no run or comparison may take these names
_SKIPPED_SUFFIXES = {".png", ".gif", ".mcap", ".lock"}


def _packed_files(out: Path, latest_only: bool = False, whole: tuple[Path, ...] = ()) -> list[Path]:
    """The files a pack holds; ``latest_only``: of each run's checkpoints only those of the update its resume starts
    from (``_resume_update``), except under ``whole``. Raises ``CheckpointError`` for a run whose seeds share none."""
    files = [path for path in sorted(out.rglob("*")) if _packable(path, out)]
    if not latest_only:
        return files
    resume_at: dict[Path, int | None] = {}  # checkpoints folder -> its run's resume update

    def kept(path: Path) -> bool:
        update = ckpt.update_of(path)
        if update is None or any(path.is_relative_to(folder) for folder in whole):
            return True
        checkpoints = path.parent.parent
        if checkpoints not in resume_at:
            resume_at[checkpoints] = _resume_update(checkpoints)
        return resume_at[checkpoints] in (None, update)

    return [path for path in files if kept(path)]


def _packable(path: Path, out: Path) -> bool:
    """Whether ``path`` (under ``out``) goes into a pack: a plain file, not a picture, log or lock."""
    if not path.is_file() or path.is_symlink():
        return False
    skipped_dir = _SKIPPED_DIRS & set(path.relative_to(out).parts[:-1])
    return not skipped_dir and path.suffix not in _SKIPPED_SUFFIXES and path.name != LOCK_NAME


def _resume_update(checkpoints: Path) -> int | None:
    """The newest update every seed under ``checkpoints`` has (``resume_updates``): where a resume of the run starts
    whatever shards its seeds are put in, so the one update a latest-only pack needs. Not each seed's newest: a
    save cut short (a kill, a full disk, a stopped Ray actor) leaves some seeds one stop ahead, and a pack of those
    newest files held no update every seed had, which resumed from update 0, pruning and cutting metrics.csv back.
    The ahead seeds' newer files are left out: a resume trains those updates again, to the same numbers. None when
    no seed is past update 0 (every checkpoint kept: they are the update-0 ones)."""
    common = resume_updates(checkpoints.parent, ckpt.list_seeds(checkpoints.parent))
    return common[0] if common else None


def snapshots_still_read(study: Study, state: StudyState, out: Path) -> tuple[Path, ...]:
    """Run directories whose older checkpoints a step still to come reads, which ``latest_only`` must keep: a run
    whose over_training step is not done (it cross-plays every kept snapshot), and the partners of an FCP run that
    has not finished training (its pool reads their mid and final snapshots): the study's ``partners_from`` run,
    or else the partner stage it trains into RUN/partners. A run counts as finished by its directory, as the
    runner judges it, not by study.json alone (a damaged result is trained again). ``study``: the one ``state``
    keeps (``kept_study``)."""

    def done(kind: str, name: str) -> bool:
        return state.steps.get(Step(kind, name).name, StepRecord()).done

    folders = []
    for run in study.runs:
        if run.name in study.over_training and not done("over_training", run.name):
            folders.append(run_dir(out, run.name))
        if not run_finished(run_dir(out, run.name)):
            partners = run_dir(out, run.partners_from) if run.partners_from else run_dir(out, run.name) / "partners"
            folders.append(partners)
    return tuple(folders)


def pack_study(out: Path, dest: Path, part_bytes: int = PART_BYTES, latest_only: bool = False) -> dict:
    """Write ``out``'s resumable state into ``dest`` (created; must be empty): parts and ``pack.json``.

    ``latest_only``: of each run's checkpoints only those of the newest update every seed has (``_resume_update``),
    which is all that resuming training needs (a 10-seed PPO-CNN checkpoint is about 13.5 MB), except where a step
    still to come reads older snapshots (``snapshots_still_read``: over-training cross-play not done, FCP partners
    of an unfinished run), which are packed whole -- for a study with 11 kept snapshots and over-training, about
    150 MB per 10-seed CNN run, more than a GPU window carries: run such a study where its pack need not travel.
    What no step reads is left behind (``ocv2 export --checkpoint mid`` will not find it): publish the snapshots
    first (``ocv2 study publish``) if they matter.

    Everything is checked before anything is written -- study.json field by field, every packed checkpoint's
    checksum (a pack is what a later session resumes from, so a damaged one must not replace a good one) -- and
    the parts are written beside ``dest`` and moved in whole: a failure leaves ``dest`` as it was. The study's lock
    is held throughout: a study that another process is running is refused (``_study_locked``).
    """
    out, dest = Path(out), Path(dest).resolve()  # resolved: "." has no name to stage beside
    if read_state(out) is None:
        raise StudyError(f"{out}: not a study directory (no study.json)")
    with _study_locked(out):
        return _pack_locked(out, dest, part_bytes, latest_only)


_RUNNING_ADVICE = (
    "stop it first (Ctrl-C or SIGTERM stops it once its chunk in flight is saved; study_state/stop_and_pack.py stops "
    "and packs), then pack again; nothing was packed"
)


@contextmanager
def _study_locked(out: Path) -> Iterator[None]:
    """Hold ``out``'s study lock (``DirLock``, as ``study run`` takes it) while packing: a running study prunes
    checkpoints (a listed file gone before it is read) and saves its seeds one at a time (a latest-only pack could
    catch them at different updates). A study directory this user cannot write (no lock file can be made) is
    packed if no other process holds its lock."""
    lock = DirLock(out)
    try:
        lock.acquire(advice=_RUNNING_ADVICE)
    except RunDirError as error:
        raise StudyError(str(error)) from None
    except OSError:
        if lock.held_elsewhere():
            raise StudyError(f"{out}: in use by another ocv2 process; {_RUNNING_ADVICE}") from None
    try:
        yield
    finally:
        lock.release()


def _pack_locked(out: Path, dest: Path, part_bytes: int, latest_only: bool) -> dict:
    """``pack_study`` with the study's lock held: study.json is read again, as no other process can change it now."""
    state = read_state(out)
    if state is None:
        raise StudyError(f"{out}: not a study directory (no study.json)")
    study = kept_study(state, out)
    missing = missing_runs(study, out, state)
    if missing:  # a pack without it would look resumable and train that run again from update 0
        raise StudyError(f"{missing[0]}; nothing was packed")
    if dest.is_relative_to(out.resolve()):
        raise StudyError(
            f"{dest}: inside the study directory {out} (a later pack would hold this one); choose another --out"
        )
    check_folder(dest, "a pack folder")
    if dest.exists() and any(dest.iterdir()):
        raise StudyError(f"{dest}: exists and is not an empty folder; choose another --out")
    if part_bytes < 1:
        raise StudyError(f"part size must be positive, got {part_bytes}")
    whole = snapshots_still_read(study, state, out) if latest_only else ()
    try:
        files = _packed_files(out, latest_only, whole)
    except ckpt.CheckpointError as error:  # a run whose seeds share no update: its pack could not resume
        raise StudyError(f"{error}; nothing was packed") from None
    for path in files:
        try:
            if ckpt.update_of(path) is not None:
                ckpt.read(path)
            elif path.name == "config.yaml":  # a run's: what resuming and every later step reads first
                RunDir(path.parent).load_config()
            elif path.name == "manifest.json":
                RunDir(path.parent).read_manifest()
        except (ckpt.CheckpointError, RunDirError) as error:
            raise StudyError(f"{error}; nothing was packed") from None
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for path in files:
            tar.add(path, arcname=str(path.relative_to(out)))
    data = buffer.getvalue()
    try:
        # Whole or not at all; dest is new or empty (checked). pack.json, which says the pack is complete, moves last.
        with staged_folder(dest, ".packing", markers=[PACK_NAME]) as staging:
            parts = []
            for index, start in enumerate(range(0, max(len(data), 1), part_bytes)):
                chunk = data[start : start + part_bytes]
                name = f"study.tar.gz.{index:03d}"
                (staging / name).write_bytes(chunk)
                parts.append({"file": name, "bytes": len(chunk), "sha256": hashlib.sha256(chunk).hexdigest()})
            record = {"study": state.study, "files": len(files), "bytes": len(data), "latest_only": latest_only}
            if latest_only:  # the run directories packed with every checkpoint, because a step to come reads them
                record["kept_whole"] = [str(folder.relative_to(out)) for folder in whole if folder.is_dir()]
            record["parts"] = parts
            (staging / PACK_NAME).write_text(json.dumps(record, indent=1))
    except OSError as error:
        raise StudyError(f"{dest}: cannot write the pack ({error.strerror or error}); nothing was packed") from None
    return record


def read_pack(source: Path) -> tuple[dict, bytes]:
    """``pack.json`` of ``source`` and the packed bytes, every part checked against its sha256."""
    source = Path(source)
    if source.exists() and not source.is_dir():
        raise StudyError(f"{source}: a file, not a pack folder (the folder holding {PACK_NAME} and its parts)")
    try:
        record = boundedjson.loads((source / PACK_NAME).read_text())
        parts = record["parts"]
    except FileNotFoundError:
        raise StudyError(f"{source}: no {PACK_NAME} (not a packed study, or packing did not finish)") from None
    except (ValueError, KeyError, TypeError) as error:  # ValueError: not JSON, not UTF-8, or nested too deep
        raise StudyError(f"{source / PACK_NAME}: unreadable ({error})") from None
    if not isinstance(parts, list) or not all(isinstance(part, dict) for part in parts):
        raise StudyError(f"{source / PACK_NAME}: 'parts' must be a list of {{file, bytes, sha256}} entries")
    _check_record(record, source / PACK_NAME)
    chunks = []
    for part in parts:
        path = source / str(part.get("file", ""))
        if path.parent != source:
            raise StudyError(f"{source / PACK_NAME}: part {part.get('file')!r} lies outside the pack folder")
        if not path.is_file():
            raise StudyError(f"{source}: part {part.get('file')!r} named by {PACK_NAME} is missing")
        chunk = path.read_bytes()
        if hashlib.sha256(chunk).hexdigest() != part.get("sha256"):
            raise StudyError(f"{path}: sha256 does not match {PACK_NAME} (damaged or from another pack)")
        chunks.append(chunk)
    data = b"".join(chunks)
    if len(data) != record["bytes"]:
        raise StudyError(f"{source / PACK_NAME}: says {record['bytes']:,} bytes, its parts hold {len(data):,}")
    return record, data


def _check_record(record: dict, where: Path) -> None:
    """pack.json's own fields, as ``pack_study`` writes them, before any part is read."""
    if not isinstance(record.get("study"), str) or not record["study"]:
        raise StudyError(f"{where}: 'study' must be the study's name, found {record.get('study')!r}")
    for key in ("files", "bytes"):
        value = record.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise StudyError(f"{where}: {key!r} must be a count of 0 or more, found {value!r}")
    names = [str(part.get("file", "")) for part in record["parts"]]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise StudyError(f"{where}: part {repeated[0]!r} is listed more than once")


def _check_contents(source: Path, record: dict, data: bytes) -> None:
    """The packed tar against pack.json's ``record``, before anything is written: as many files as it says, and a
    study.json of the study it names (a pack.json edited or put beside another pack's parts is refused)."""
    where = source / PACK_NAME
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
            members = tar.getmembers()
            packed = next((m for m in members if m.name == "study.json" and m.isfile()), None)
            text = tar.extractfile(packed).read() if packed is not None else None
    except (tarfile.TarError, OSError, EOFError, zlib.error) as error:
        raise StudyError(f"{source}: cannot unpack ({error}); nothing was written") from None
    if len(members) != record["files"]:
        raise StudyError(f"{where}: says {record['files']} files, its parts hold {len(members)}; nothing was written")
    if text is None:
        raise StudyError(f"{source}: the pack holds no study.json; nothing was written")
    try:
        state = StudyState.from_json(boundedjson.loads(text.decode()), source / "study.json (packed)")
    except (ValueError, UnicodeDecodeError) as error:  # StudyError is a ValueError
        raise StudyError(f"{source}: its packed study.json is unreadable ({error}); nothing was written") from None
    if state.study != record["study"]:
        raise StudyError(
            f"{where}: names study {record['study']!r}, its packed study.json study {state.study!r}; "
            "nothing was written"
        )


def unpack_study(source: Path, out: Path) -> dict:
    """Unpack the packed study in ``source`` into ``out`` (which must not exist). Returns pack.json's record, once
    the packed files are checked against it (``_check_contents``)."""
    out = Path(out)
    check_folder(out)  # not a file, nor under one
    if out.exists():
        raise StudyError(f"{out}: exists; unpack into a new directory (nothing was written)")
    record, data = read_pack(source)
    _check_contents(Path(source), record, data)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise StudyError(f"{out}: cannot unpack here ({error.strerror or error}); nothing was written") from None
    try:
        with staged_folder(out, ".unpacking") as staging:  # whole or not at all
            with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
                tar.extractall(staging, filter="data")  # no absolute paths, links out or devices
    except (tarfile.TarError, OSError, EOFError, zlib.error) as error:  # EOFError, zlib: a cut or bad gzip stream
        raise StudyError(f"{source}: cannot unpack ({error}); nothing was written") from None
    return record
