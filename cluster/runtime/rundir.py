"""The run directory every backend writes:

    RUN_DIR/config.yaml       resolved config (the run's identity: its fingerprint guards checkpoints)
            manifest.json     progress for --resume: status, updates done, snapshots, stage
            environment.json  versions, git commit, devices and argv of every driver that ran it
            metrics.csv       one row per seed per update
            .lock             held (flock) by the one driver writing the run
            checkpoints/seed_<i>/update_<n>.msgpack
            xp/matrix.csv  xp/episodes.csv  xp/summary.json  xp/heatmap.png
            plots/training.png   gifs/*.gif

``RunDir.open`` is the one way in for a driver that writes (checks, lock, stale temporaries);
``RunDir.existing`` the one way in for a reader (checks only).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import fcntl
import io
import json
import logging
import math
import os
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cluster.runtime.environment import environment_record
from ocv2 import boundedjson
from ocv2.atomic import atomic_write, is_temporary, remove_stale_temporaries
from population import checkpoints as ckpt
from population.config import Config, ConfigError, dump_config, load_run_config

log = logging.getLogger(__name__)

METRIC_FIELDS = (
    "seed",
    "update",
    "env_steps",
    "sparse_return",
    "shaped_return",
    "episodes",
    "loss",
    "actor_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "clip_frac",
    "lr",
    "shaping_coef",
    "steps_per_s",
    "wall_s",
)
LOCK_NAME = ".lock"


class MetricsRow(NamedTuple):
    """One row of ``metrics.csv``: one seed's numbers after one update, typed."""

    seed: int
    update: int
    env_steps: int  # this seed's environment steps so far (the x axis of training curves)
    values: dict[str, float]  # every other column by name; NaN where nothing was measured (no episode ended yet)

    @classmethod
    def of(cls, row: Mapping) -> MetricsRow:
        """From a row as ``metric_rows`` builds it or as ``csv`` reads it back (strings, "" = no value)."""
        return cls(
            int(float(row["seed"])),
            int(float(row["update"])),
            int(float(row["env_steps"])),
            {key: float_or_nan(value) for key, value in row.items() if key not in _INDEX_FIELDS},
        )


_INDEX_FIELDS = ("seed", "update", "env_steps")


def float_or_nan(value) -> float:
    """``value`` as a float; NaN for what holds no number: "" (nothing measured, e.g. no episode finished
    yet), None or a missing column."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


class RunDirError(ValueError):
    """A run directory that cannot be used as asked (exists, belongs to another config, ...)."""


class DirLock:
    """The exclusive lock of one directory (a run directory, a study directory) held by the one ocv2
    process writing it: ``flock`` on ``DIR/.lock``, which holds the holder's pid. Advisory, and released
    by the kernel when the holder exits or dies (no stale lock after a kill); NFS and some other network
    file systems may not honour it."""

    def __init__(self, path):
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self, wait: bool = False, advice: str = "wait for it to finish") -> None:
        """Take the lock (nothing when this object holds it already). Raises ``RunDirError`` naming the
        directory and the pid that holds it, then ``advice``; with ``wait``, says who holds it and blocks
        until it is free instead. Raises ``OSError`` when ``DIR/.lock`` cannot be opened."""
        if self._fd is not None:
            return
        fd = os.open(self.path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                os.close(fd)
                raise
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            if not wait:
                os.close(fd)
                raise RunDirError(f"{self.path}: in use by another ocv2 process (pid {holder}); {advice}") from None
            _warn(f"{self.path}: in use by another ocv2 process (pid {holder}); waiting for it to finish")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
            except BaseException:
                os.close(fd)
                raise
        try:
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)  # reading the holder's pid moved the offset
            os.write(fd, f"{os.getpid()}\n".encode())
        except BaseException:  # e.g. a full disk: an open fd would keep the lock, and we would blame "another" process
            os.close(fd)
            raise
        self._fd = fd

    def release(self) -> None:
        """Let the lock go (nothing when this object does not hold it)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def held_elsewhere(self) -> bool:
        """Whether another process holds the lock now (or the lock file cannot be read). Writes nothing: a
        shared lock is tried on the file opened read-only and let go at once, so ``study status`` may look at a
        directory it cannot write, and no holder's pid is replaced by its own."""
        if self._fd is not None:
            return False
        try:
            fd = os.open(self.path / LOCK_NAME, os.O_RDONLY)
        except FileNotFoundError:  # whoever holds the lock made the file first
            return False
        except OSError:
            return True
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return True
        finally:
            os.close(fd)  # closing lets a shared lock go
        return False

    def __del__(self):
        self.release()


class RunDir:
    """Paths and files of one run directory. ``RunDir(path)`` checks nothing; use ``open``/``existing``."""

    def __init__(self, path):
        self.path = Path(path)
        self._lock: DirLock | None = None
        self._metrics: tuple[list[str], list[list]] | None = None  # (columns, rows) of metrics.csv

    # opening ----------------------------------------------------------------------------------------
    @classmethod
    def open(cls, path, config: Config, resume: bool = False) -> tuple[RunDir, bool]:
        """(the run directory, resuming?) for a driver that trains ``config`` into ``path``.

        Takes the run's lock (held until ``close``), then checks the directory (see ``create``) and
        removes temporaries that an interrupted write left behind.
        """
        run = cls(Path(path).resolve())  # absolute: actors on other nodes/working dirs get the same path
        resuming = run.create(config, resume=resume)
        return run, resuming

    @classmethod
    def existing(cls, path) -> RunDir:
        """A run directory to read (``ocv2 xp``, reports, FCP partners): it must hold a usable run."""
        run = cls(path)
        run._check_not_a_file()
        if not run.config_path.exists():
            raise RunDirError(f"{path}: not an ocv2 run directory (no config.yaml)")
        run.read_manifest()  # an empty or corrupt manifest is reported here, not deep in a later step
        return run

    def create(self, config: Config, resume: bool = False) -> bool:
        """Lock the directory and prepare it for ``config``. Returns True when resuming an existing run.

        A new run needs a missing or empty directory; ``resume`` needs the same config fingerprint.
        """
        self._check_not_a_file("; choose another --out")
        if resume and not self.config_path.exists():
            raise RunDirError(f"{self.path}: nothing to resume (no config.yaml)")
        made = not self.path.exists()
        self.path.mkdir(parents=True, exist_ok=True)
        self.lock()
        try:
            resuming = self._prepare(config, resume)
            self._record_environment(resuming)
        except BaseException:
            if not self.config_path.exists():  # refused before it became a run: leave nothing behind
                (self.path / LOCK_NAME).unlink(missing_ok=True)
                if made:
                    with contextlib.suppress(OSError):  # only if empty; the original error matters more
                        self.path.rmdir()
            self.close()
            raise
        return resuming

    def _prepare(self, config: Config, resume: bool) -> bool:
        if self.config_path.exists():
            existing = self.load_config()
            if existing.fingerprint() != config.fingerprint():
                changed = trained_keys_changed(existing, config)
                shown = "; ".join(changed[:5]) + (f"; and {len(changed) - 5} more" if len(changed) > 5 else "")
                advice = "choose another --out"
                if extension_problem(existing, config) is None:  # a later stop on the same schedule
                    advice = "add --extend to train this truncated run on along its schedule, or " + advice
                raise RunDirError(
                    f"{self.path}: holds a run of a different config (fingerprint "
                    f"{existing.fingerprint()} vs {config.fingerprint()}{': ' + shown if shown else ''}); "
                    f"{advice}"
                )
            if not resume:
                raise RunDirError(
                    f"{self.path}: already holds a run; pass --resume to continue it or choose another --out"
                )
            self.read_manifest()
            for path in remove_stale_temporaries(self.path):  # safe: the lock keeps other writers out
                _warn(f"{self.path}: removed {path.relative_to(self.path)} (left by an interrupted write)")
            return True
        if any(p.name != LOCK_NAME and not is_temporary(p) for p in self.path.iterdir()):
            raise RunDirError(
                f"{self.path}: exists and is not an ocv2 run directory (no config.yaml); choose another --out"
            )
        if resume:
            raise RunDirError(f"{self.path}: nothing to resume (no config.yaml)")
        remove_stale_temporaries(self.path)
        dump_config(config, self.config_path)  # first: a directory with a config.yaml can be resumed
        self.write_manifest({"status": "created", "created": time.time()})
        return False

    def _check_not_a_file(self, advice: str = "") -> None:
        if self.path.exists() and not self.path.is_dir():
            raise RunDirError(f"{self.path}: is a file, not a run directory{advice}")
        for parent in self.path.parents:  # --out DIR/sub with DIR a file: mkdir would fail with ENOTDIR
            if parent.exists():
                if not parent.is_dir():
                    raise RunDirError(
                        f"{self.path}: cannot be a run directory: {parent} is a file, not a directory{advice}"
                    )
                break

    # the lock -----------------------------------------------------------------------------------------
    def lock(self, wait: bool = False, advice: str = "wait for it to finish or stop it before resuming") -> None:
        """Take the run's exclusive lock (``DirLock``), or fail naming the process that holds it
        (``advice`` follows); with ``wait``, say who holds it and block until it is free."""
        if self._lock is None:
            self._lock = DirLock(self.path)
        self._lock.acquire(wait=wait, advice=advice)

    def close(self) -> None:
        """Release the lock (also released when the process exits)."""
        if self._lock is not None:
            self._lock.release()

    def __del__(self):
        self.close()

    # paths ------------------------------------------------------------------------------------------
    @property
    def config_path(self) -> Path:
        return self.path / "config.yaml"

    @property
    def manifest_path(self) -> Path:
        return self.path / "manifest.json"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.csv"

    @property
    def environment_path(self) -> Path:
        return self.path / "environment.json"

    def sub(self, *parts) -> Path:
        out = self.path.joinpath(*parts)
        out.parent.mkdir(parents=True, exist_ok=True)
        return out

    def subdir(self, *parts) -> Path:
        """A directory under the run directory, created if missing."""
        out = self.path.joinpath(*parts)
        out.mkdir(parents=True, exist_ok=True)
        return out

    # config, manifest, environment ------------------------------------------------------------------
    def load_config(self) -> Config:
        try:
            return load_run_config(self.path)
        except ConfigError as error:
            raise RunDirError(f"{self.path}: its config.yaml is unusable: {error}") from None

    def read_manifest(self) -> dict:
        try:
            text = self.manifest_path.read_text()
        except FileNotFoundError:
            return {}
        try:
            data = boundedjson.loads(text)
        except ValueError as error:  # not JSON, or nested deeper than any manifest ocv2 writes
            what = "is empty" if not text.strip() else f"is not valid JSON ({error})"
            raise RunDirError(
                f"{self.manifest_path}: {what}; restore it from a backup or delete it to resume from the checkpoints"
            ) from None
        if not isinstance(data, dict):
            raise RunDirError(f"{self.manifest_path}: holds a JSON {type(data).__name__}, not an object")
        try:
            ckpt.manifest_extensions(data, self.manifest_path)
        except ckpt.CheckpointError as error:
            raise RunDirError(str(error)) from None
        return data

    def write_manifest(self, data: dict) -> None:
        atomic_write(self.manifest_path, strict_json(data))  # fsynced

    def update_manifest(self, **changes) -> dict:
        data = self.read_manifest()
        data.update(changes)
        self.write_manifest(data)
        return data

    def _record_environment(self, resuming: bool) -> None:
        """Append this driver's versions, commit, devices and argv to ``environment.json``."""
        history = []
        if resuming and self.environment_path.exists():
            try:
                history = boundedjson.loads(self.environment_path.read_text()).get("drivers", [])
            except (ValueError, AttributeError):
                _warn(f"{self.environment_path}: unreadable; starting a new record")
        history.append(environment_record())
        write_json(self.environment_path, {"drivers": history})

    def amend_environment(self, **fields) -> None:
        """Add ``fields`` to this driver's record in ``environment.json`` (the last one), e.g. its workers once
        they have started."""
        try:
            data = boundedjson.loads(self.environment_path.read_text())
            history = data["drivers"]
            history[-1].update(fields)
        except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError):
            _warn(f"{self.environment_path}: unreadable; not amended with {', '.join(fields)}")
            return
        write_json(self.environment_path, {"drivers": history})

    # metrics ----------------------------------------------------------------------------------------
    def append_metrics(self, rows: list[dict]) -> None:
        """Add ``rows`` to ``metrics.csv``, rewriting the file atomically (a kill never leaves a torn row).

        The table is kept here after the first call (the driver holding the lock is the only writer),
        so each chunk costs one write, not a read and a write. A driver sets it with ``restart_metrics``
        first, in the run's own column order.
        """
        if self._metrics is None:  # a writer that did not start with restart_metrics (tools, tests)
            found = self._read_metrics()
            fields = found.fields or default_metric_fields(rows)
            self._metrics = (fields, [[row.get(k, "") for k in fields] for row in found.rows])
        fields, table = self._metrics
        unknown = sorted({key for row in rows for key in row} - set(fields))
        if unknown:
            raise RunDirError(f"{self.metrics_path}: rows with columns {unknown} that the file does not have")
        table = table + [[row.get(k, "") for k in fields] for row in rows]
        write_csv(self.metrics_path, fields, table)
        self._metrics = (fields, table)

    def metrics_to_resume(self, fields: list[str]) -> MetricsFile:
        """``metrics.csv`` as a resume finds it, read and checked, nothing rewritten: ``RunDirError`` naming the
        line for a header of other columns than ``fields`` or a damaged row before the last (ocv2 rewrites the
        file whole, so no kill leaves one, and rows older than the last chunk are in no checkpoint). A torn
        last row (an older, appending writer's kill) is reported and left for the resume to drop and refill."""
        found = self._read_metrics()
        if found.fields and sorted(found.fields) != sorted(fields):
            raise RunDirError(f"{self.metrics_path}: {_header_problem(found.fields, fields)}; {_RESTORE}")
        if found.damaged:
            shown = "; ".join(_damaged_line(number, text) for number, text in found.damaged[:5])
            more = f"; and {len(found.damaged) - 5} more such lines" if len(found.damaged) > 5 else ""
            raise RunDirError(
                f"{self.metrics_path}: the file is damaged: {shown}{more}. No interrupted write leaves such a line "
                f"before the last (ocv2 rewrites this file whole), and rows before the last chunk cannot be rebuilt "
                f"from the checkpoints: {_RESTORE}"
            )
        self._warn_torn(found)
        return found

    def restart_metrics(self, fields: list[str], rows: list[dict]) -> None:
        """Make ``rows`` the table that ``append_metrics`` extends, in the columns ``fields``, and write it when
        ``metrics.csv`` holds anything else (rows a resume dropped or refilled, columns in another order)."""
        table = [[row.get(k, "") for k in fields] for row in rows]
        try:
            before = self.metrics_path.read_bytes()  # bytes: csv ends its lines with \r\n
        except FileNotFoundError:
            before = None
        if (before is not None or table) and before != csv_text(fields, table).encode():
            write_csv(self.metrics_path, fields, table)
        self._metrics = (fields, table)

    def read_metrics(self) -> list[dict]:
        """The complete rows of ``metrics.csv``; a torn or damaged row is skipped with a warning."""
        found = self._read_metrics()
        self._warn_torn(found)
        for number, text in found.damaged:
            _warn(f"{self.metrics_path}: the file is damaged: {_damaged_line(number, text)}; dropped")
        return found.rows

    def _warn_torn(self, found: MetricsFile) -> None:
        for number, why in found.torn:
            _warn(f"{self.metrics_path}: line {number} is incomplete (an interrupted write); dropped{why}")

    def _read_metrics(self) -> MetricsFile:
        """``metrics.csv`` as it is, sorted into complete rows, a torn last row and damaged rows; says nothing.
        Torn rows come from a kill in the middle of a write by an appending writer (older versions; this one
        rewrites the file atomically)."""
        try:
            text = self.metrics_path.read_text()
        except FileNotFoundError:
            return MetricsFile([], [], [], [])
        except UnicodeDecodeError as error:  # ocv2 writes ASCII: bytes that are not text are damage
            raise RunDirError(
                f"{self.metrics_path}: damaged: byte {error.start} is not UTF-8 text ({error.reason})"
            ) from None
        lines = text.splitlines(keepends=True)
        torn = []
        if lines and not lines[-1].endswith("\n"):  # the last row was cut short
            torn.append((len(lines), ""))
            lines = lines[:-1]
        reader = csv.DictReader(io.StringIO("".join(lines), newline=""))
        records = list(reader)
        rows, damaged = [], []
        for number, row in enumerate(records, start=2):
            if (
                None in row
                or None in row.values()
                or not _is_int(row.get("update"))
                or not _is_int(row.get("seed"))
                or not _is_count_or_blank(row.get("env_steps"))
            ):
                if number == len(records) + 1:  # the last row: what an appending writer's kill leaves
                    torn.insert(0, (number, _REFILLED))
                else:  # ocv2 rewrites the file atomically: a bad row before the last is damage
                    damaged.append((number, _shown(row)))
                continue
            rows.append(row)
        return MetricsFile(list(reader.fieldnames or []), rows, torn, damaged)


class MetricsFile(NamedTuple):
    """``metrics.csv`` as read, before anything is dropped or rewritten."""

    fields: list[str]  # its header (empty: no file, or an empty one)
    rows: list[dict]  # its complete rows, in the file's order
    torn: list[tuple[int, str]]  # (line, note) of a last row cut short: an older, appending writer's kill
    damaged: list[tuple[int, str]]  # (line, the row as it reads) of bad rows before the last: damage, not a kill


_REFILLED = " (--resume refills it from the checkpoint if it belongs to the last chunk)"
_RESTORE = (
    "restore the file from a copy (`ocv2 study pack` keeps one) or repair the line, and resume again; nothing was "
    "trained and the file was not changed"
)


def _damaged_line(number: int, text: str) -> str:
    return f"line {number} (row {number - 1}) is not a complete metrics row ({text})"


def _header_problem(found: list[str], fields: list[str]) -> str:
    """What is wrong with a header (line 1) whose columns are not the run's."""
    extra = [f for f in found if f not in fields]
    missing = [f for f in fields if f not in found]
    parts = ([f"columns {extra} this run does not write"] if extra else []) + (
        [f"no columns {missing}"] if missing else []
    )
    return f"line 1, the header, has {' and '.join(parts) or 'a column twice'}"


def enclosing_run(path) -> Path | None:
    """The run directory (config.yaml beside manifest.json or checkpoints/) that holds ``path``, if any."""
    for folder in Path(path).resolve().parents:
        if (folder / "config.yaml").is_file() and (
            (folder / "manifest.json").is_file() or (folder / "checkpoints").is_dir()
        ):
            return folder
    return None


def trained_keys_changed(run: Config, now: Config) -> list[str]:
    """The keys behind a fingerprint mismatch ("ppo.lr: 0.0004 in the run, 0.01 now"): every key of the
    fingerprinted sections (``Config.fingerprinted``) whose value differs."""
    before, after = run.fingerprinted(), now.fingerprinted()
    return [
        f"{key}: {before.get(key)!r} in the run, {after.get(key)!r} now"
        for key in sorted(set(before) | set(after))
        if before.get(key) != after.get(key)
    ]


#: The config keys an extension may change: the stop, and the schedule's length only in how it is written (a
#: run extended to its schedule's end is the whole run, whose config leaves ``schedule_timesteps`` unset).
EXTENDED_KEYS = ("ppo.total_timesteps", "ppo.schedule_timesteps")


def extension_problem(run: Config, now: Config) -> str | None:
    """Why ``run`` (a run's config.yaml) cannot be extended to ``now`` (``cluster.runtime.extend``: a later stop on
    the same schedule); None when it can (or ``now`` is it)."""
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


def _warn(message: str) -> None:
    log.warning(message)


def _shown(row: dict) -> str:
    """A damaged row as it reads, short enough for one line."""
    values = [str(v) for k, v in row.items() if k is not None and v is not None] + [str(v) for v in row.get(None, [])]
    text = ",".join(values)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(text) -> bool:
    try:
        int(float(text))
        return True
    except (TypeError, ValueError, OverflowError):  # OverflowError: "1e400" reads as inf
        return False


def _is_count_or_blank(text) -> bool:
    """A column ocv2 writes as a whole count (env_steps): absent, blank or a finite number; "1e400" or "inf" is damage
    that would end a reader's ``int()`` in an OverflowError."""
    return text is None or not str(text).strip() or math.isfinite(float_or_nan(text))


class SeedCurves(NamedTuple):
    """``metrics.csv`` columns as seeds x updates arrays (NaN where a seed has no value, e.g. no episode
    had finished yet): what the training plot and ``ocv2 report`` draw."""

    seeds: list[int]
    updates: list[int]
    env_steps: np.ndarray  # [U]: the largest env_steps any seed reported at the update
    values: dict[str, np.ndarray]  # field -> [S, U]


def seed_curves(rows: list[dict], fields=("sparse_return",)) -> SeedCurves:
    """The one aggregation of per-seed metrics rows into curves (rows whose seed or update is not a
    number are skipped)."""
    rows = [r for r in rows if _is_int(r.get("seed")) and _is_int(r.get("update"))]
    seeds = sorted({int(float(r["seed"])) for r in rows})
    updates = sorted({int(float(r["update"])) for r in rows})
    seed_index, update_index = {s: k for k, s in enumerate(seeds)}, {u: k for k, u in enumerate(updates)}
    values = {field: np.full((len(seeds), len(updates)), np.nan) for field in fields}
    env_steps = np.full((len(seeds), len(updates)), np.nan)
    for r in rows:
        at = seed_index[int(float(r["seed"]))], update_index[int(float(r["update"]))]
        env_steps[at] = float_or_nan(r.get("env_steps"))
        for field in fields:
            values[field][at] = float_or_nan(r.get(field))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an update no seed reported env_steps for: NaN
        steps = np.nanmax(env_steps, axis=0) if rows else np.zeros(0)
    return SeedCurves(seeds, updates, steps, values)


def recipe_labels(layout) -> list[str]:
    """The names of a layout's recipes in ``metrics.csv`` columns ("0+0+1"), in the layout's order."""
    return ["+".join(map(str, recipe)) for recipe in layout.possible_recipes]


def metric_fields(labels: list[str]) -> list[str]:
    """The columns of ``metrics.csv`` in the order ``metric_rows`` makes them: the one header of a run, whether it
    ran straight through or was resumed (rows that come back from a checkpoint's meta have their keys sorted)."""
    return [*METRIC_FIELDS, *(_recipe_column(label) for label in labels)]


def default_metric_fields(rows: list[dict]) -> list[str]:
    """Columns for rows written without the run's own list (``metric_fields``): ``METRIC_FIELDS``, then the
    others sorted."""
    others = sorted({key for row in rows for key in row} - set(METRIC_FIELDS))
    return [*METRIC_FIELDS, *others]


def _recipe_column(label: str) -> str:
    return f"return_recipe_{label}"


def metric_rows(seeds, metrics, steps_per_s: float, wall_s: float, recipe_labels: list[str]) -> list[dict]:
    """Rows for ``metrics.csv`` from population metrics [S, n] (numpy)."""
    rows = []
    loss = metrics.loss
    for s, seed in enumerate(seeds):
        for u in range(np.shape(metrics.update)[1]):
            row = {
                "seed": seed,
                "update": int(metrics.update[s, u]),
                "env_steps": int(metrics.env_steps[s, u]),
                "sparse_return": _num(metrics.sparse_return[s, u]),
                "shaped_return": _num(metrics.shaped_return[s, u]),
                "episodes": int(metrics.episodes[s, u]),
                "loss": _num(loss.total[s, u]),
                "actor_loss": _num(loss.actor[s, u]),
                "value_loss": _num(loss.value[s, u]),
                "entropy": _num(loss.entropy[s, u]),
                "approx_kl": _num(loss.approx_kl[s, u]),
                "clip_frac": _num(loss.clip_frac[s, u]),
                "lr": _num(metrics.lr[s, u]),
                "shaping_coef": _num(metrics.shaping_coef[s, u]),
                "steps_per_s": round(steps_per_s, 1),
                "wall_s": round(wall_s, 2),
            }
            for r, label in enumerate(recipe_labels):
                row[_recipe_column(label)] = _num(metrics.recipe_returns[s, u, r])
            rows.append(row)
    return rows


def _num(value) -> float | str:
    value = float(value)
    return "" if math.isnan(value) else round(value, 6)


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def csv_text(header, rows) -> str:
    """What ``write_csv`` writes."""
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def write_csv(path: Path, header, rows) -> None:
    """A CSV file written atomically (a reader sees the old or the new file, never half of one)."""
    atomic_write(path, csv_text(header, rows))  # CSV rows keep their \r\n


MATRIX_CORNER = "seat0\\seat1"


class LabelledMatrix(NamedTuple):
    """A cross-play matrix as ``matrix.csv`` holds it: seat-0 players down the rows, seat-1 across."""

    rows: list[str]
    cols: list[str]
    values: np.ndarray  # float64 [len(rows), len(cols)]; NaN where a cell has no number


def write_matrix_csv(path: Path, values, rows, cols, corner: str = MATRIX_CORNER) -> None:
    """``matrix.csv``: a corner cell, the seat-1 labels, then one row per seat-0 player (mean return, 4 places)."""
    values = np.asarray(values, np.float64)
    write_csv(
        path,
        [corner] + list(cols),
        [[rows[i]] + [round(float(v), 4) for v in values[i]] for i in range(len(rows))],
    )


def read_matrix_csv(path) -> LabelledMatrix:
    """Read what ``write_matrix_csv`` wrote; ``ValueError`` naming the file, row and column of a bad cell.
    An empty cell or ``nan`` reads as NaN (a pair that has no number), anything else that is not a number
    is an error rather than a silent NaN."""
    path = Path(path)
    with open(path, newline="") as handle:
        table = [row for row in csv.reader(handle) if row]
    if not table or len(table[0]) < 2:
        raise ValueError(f"{path}: not a cross-play matrix (no header row with seat-1 labels)")
    cols = table[0][1:]
    values = np.full((len(table) - 1, len(cols)), np.nan)
    for i, row in enumerate(table[1:]):
        if len(row) != len(cols) + 1:
            raise ValueError(f"{path}: row {i + 2} has {len(row) - 1} cells, the header has {len(cols)}")
        for j, cell in enumerate(row[1:]):
            if cell.strip() == "":
                continue
            try:
                values[i, j] = float(cell)
            except ValueError:
                raise ValueError(f"{path}: row {i + 2}, column {cols[j]!r}: {cell!r} is not a number") from None
    return LabelledMatrix([row[0] for row in table[1:]], cols, values)


def strict_json(data) -> str:
    """``data`` as strict JSON: a NaN or infinite number becomes ``null``.

    Python's ``json`` writes bare ``NaN``/``Infinity`` by default, which JSON does not allow: ``jq``,
    JavaScript's ``JSON.parse`` and most other readers reject the whole file. An undefined number here
    (an interval of a single seed, a mean over no episode) is therefore ``null``.
    """
    return json.dumps(_finite_or_none(data), indent=2, default=_json_default, allow_nan=False)


def _finite_or_none(value):
    if isinstance(value, dict):
        return {key: _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(item) for item in value]
    if isinstance(value, np.ndarray):
        return _finite_or_none(value.tolist())
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def write_json(path: Path, data) -> None:
    """``data`` as strict JSON (``strict_json``), written atomically."""
    atomic_write(path, strict_json(data))
