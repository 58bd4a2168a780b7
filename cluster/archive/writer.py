"""Writing archives: ``ArchiveWriter`` appends whole episodes to ``PATH.partial``, renamed when finished."""

from __future__ import annotations

import base64
import json
import os
import time

import jax
import numpy as np

from cluster.archive.format import (
    COMPRESSION,
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    FORMAT_VERSION,
    FRAMES_TOPIC,
    LIBRARY,
    MAX_CHUNK_BYTES,
    MCAP_AVAILABLE,
    PARTIAL_SUFFIX,
    PROFILE,
    RAW_IMAGE_SCHEMA,
    RESERVED_KEYS,
    STATE_NAMES,
    STATE_TREEDEF,
    STEP_ENCODING,
    STEP_TOPIC,
    TRANSITION_FIELDS,
    ArchiveError,
    field_table,
    layout_spec,
    require_mcap,
    to_json,
)
from ocv2 import boundedjson
from ocv2.atomic import fsync_folder
from ocv2.layouts import Layout, get_layout
from ocv2.render import render_frames
from ocv2.state import State

if MCAP_AVAILABLE:  # without it, Output and ArchiveWriter raise require_mcap's error (format.py)
    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel, Schema
    from mcap.writer import CompressionType, IndexType, Writer


class Output:
    """An MCAP file written as ``PATH.partial`` and renamed to ``PATH`` once finished.

    ``committed`` is the file size after the last ``commit``: everything before it is whole records.
    After a write error ``abandon`` cuts the file back to it, so the ``.partial`` left behind ends
    with the last complete episode instead of a torn chunk.
    """

    def __init__(
        self,
        path,
        *,
        chunk_size: int,
        compression: str,
        overwrite: bool,
        fsync: bool,
        message_index: bool = True,
        suffix: str = PARTIAL_SUFFIX,
    ):
        require_mcap()
        if compression not in COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(COMPRESSION)}, got {compression!r}")
        self.path = os.fspath(path)
        self.partial = self.path + suffix
        for existing in (self.path, self.partial):
            if os.path.exists(existing) and not overwrite:
                hint = (
                    " (an unfinished archive: recover it with 'ocv2 archive recover')"
                    if existing == self.partial
                    else ""
                )
                raise ArchiveError(f"{existing!r} already exists{hint}; pass overwrite=True to replace it")
        # With overwrite, an existing PATH stays until ``finish`` replaces it in one rename: a writer that never
        # finishes (an interrupt, a write error) leaves the old file whole.
        self._fsync = fsync
        folder = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(folder, exist_ok=True)
        self._file = open(self.partial, "wb")
        try:
            index_types = IndexType.ALL if message_index else IndexType.ALL & ~IndexType.MESSAGE
            self.mcap = Writer(
                self._file,
                chunk_size=int(chunk_size),
                compression=CompressionType[compression.upper()],
                index_types=index_types,
            )
            self.mcap.start(profile=PROFILE, library=LIBRARY)
            self._file.flush()  # the header is on disk: an empty file never looks like a broken archive
        except BaseException:
            _close_quietly(self._file)
            _unlink_quietly(self.partial)  # a file without even its header holds nothing worth keeping
            raise
        self.committed = self._file.tell()
        self._schemas: dict[tuple, int] = {}
        self._channels: dict[tuple, int] = {}
        self.closed = False

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, data)
        if key not in self._schemas:
            self._schemas[key] = self.mcap.register_schema(name, encoding, data)
            self._outside_chunks(Schema(id=self._schemas[key], name=name, encoding=encoding, data=data))
        return self._schemas[key]

    def channel(self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]) -> int:
        key = (topic, encoding, schema_id, tuple(sorted(metadata.items())))
        if key not in self._channels:
            self._channels[key] = self.mcap.register_channel(topic, encoding, schema_id, metadata)
            self._outside_chunks(
                Channel(
                    id=self._channels[key],
                    topic=topic,
                    message_encoding=encoding,
                    schema_id=schema_id,
                    metadata=metadata,
                )
            )
        return self._channels[key]

    def _outside_chunks(self, record) -> None:
        """Also write a schema or channel definition as a record of its own, ahead of the chunk that
        holds it: MCAP writes it only inside that chunk, so a corrupt chunk would take the channel of
        every later episode with it (a finished file's summary repeats it; a ``.partial`` has none).
        MCAP allows identical repeats; the chunks' byte offsets stay right (same stream)."""
        builder = RecordBuilder()
        record.write(builder)
        self._file.write(builder.end())

    def commit(self):
        """End the chunk in progress and push everything to the OS (and the disk if ``fsync``)."""
        self.mcap.flush()
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self.committed = self._file.tell()

    def finish(self):
        """Write the summary and footer, close, and rename ``PATH.partial`` to ``PATH``. Idempotent.

        If that fails (a full disk), the ``.partial`` is cut back to its committed episodes and kept.
        """
        if self.closed:
            return
        try:
            self.mcap.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        except BaseException:
            self.abandon()
            raise
        self.closed = True
        self._file.close()
        os.replace(self.partial, self.path)
        # The rename made durable: a state buffer or checkpoint written after this file must not survive a power
        # loss that undoes it (a resumed run would take the archive for written).
        fsync_folder(os.path.dirname(os.path.abspath(self.path)))

    def abandon(self):
        """After a write error: close without finishing, keeping ``PATH.partial`` up to ``committed``.

        The MCAP writer's state is unknown after a failed write, so nothing more is written; the
        committed episodes stay readable and ``recover`` turns them into a finished file.
        """
        if self.closed:
            return
        self.closed = True
        _close_quietly(self._file)  # its buffered bytes fail to flush again on a full disk: dropped
        try:
            os.truncate(self.partial, self.committed)  # frees space; needs none
        except OSError:
            pass  # the torn tail stays; readers stop at it (or skip it) all the same


def _close_quietly(file) -> None:
    try:
        file.close()  # closes the descriptor even when the final flush fails
    except OSError:
        pass


def _unlink_quietly(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


class ArchiveWriter:
    """Write whole episodes to an MCAP archive; a context manager that finishes the file when its block ends
    normally.

    ::

        with ArchiveWriter("run/archive/xp.mcap") as archive:
            archive.write_episode({"method": "sp", "policies": [0, 1]}, states, actions, rewards, shaped, dones,
                                  layout="cramped_room")

    While open the data goes to ``PATH.partial``; every ``write_episode`` ends with a chunk flush, so
    a killed process loses at most the episode being written (``recover`` rescues the rest). Leaving
    the ``with`` block normally finishes the file (summary, indexes, footer) and renames it to ``PATH``;
    leaving it by an exception (Ctrl-C, an error) does not: the episodes written so far stay in the
    ``.partial`` (removed when it holds none) and an existing ``PATH`` stays as it was. The writer opens and
    closes its own file.

    A write error (a full disk: ENOSPC, EIO, a failed fsync) while an episode is written fails the
    writer: ``write_episode`` re-raises the ``OSError``, the ``.partial`` is cut back to the last
    complete episode and kept (``failed`` holds the error, ``partial_path`` the file), and every later
    ``write_episode`` raises ``ArchiveError``. Nothing is renamed to ``PATH``: finish the kept episodes
    with ``ocv2 archive recover PATH.partial`` once there is space.

    Args:
        path: the archive to create (conventionally ``*.mcap``).
        foxglove_frames: also write a ``frames`` channel of rendered states (``foxglove.RawImage``,
            JSON) for Foxglove Studio. Off by default: it makes files ~10x larger and writing slower.
        frame_tile_size: pixels per grid cell of those frames.
        chunk_size: uncompressed bytes after which a chunk is closed inside a long episode.
        compression: 'zstd' (default), 'lz4' or 'none'.
        fsync: also fsync at every episode end (survives power loss, not only a killed process;
            ``ocv2 play`` sets it: each human episode is worth a disk flush).
        overwrite: replace an existing ``PATH`` / ``PATH.partial`` instead of raising (``PATH`` only when the
            new file is finished, in one rename).
        message_index: write MCAP message indexes (default). Without them files are ~40 % smaller and
            this module reads them the same, but indexed readers such as Foxglove's rely on them.
        start_time_ns: log time of the first message (default: now). Messages are ``step_ns`` apart.
    """

    def __init__(
        self,
        path,
        *,
        foxglove_frames: bool = False,
        frame_tile_size: int = 16,
        chunk_size: int = 1 << 20,
        compression: str = "zstd",
        fsync: bool = False,
        overwrite: bool = False,
        message_index: bool = True,
        start_time_ns: int | None = None,
        step_ns: int = 100_000_000,
    ):
        require_mcap()
        if not 0 < int(chunk_size) <= MAX_CHUNK_BYTES // 4:
            raise ValueError(f"chunk_size must be in 1..{MAX_CHUNK_BYTES // 4} bytes, got {chunk_size}")
        self.path = os.fspath(path)
        self.foxglove_frames = bool(foxglove_frames)
        self.frame_tile_size = int(frame_tile_size)
        self._options = dict(
            chunk_size=chunk_size,
            compression=compression,
            overwrite=overwrite,
            fsync=fsync,
            message_index=message_index,
        )
        self._clock = time.time_ns() if start_time_ns is None else int(start_time_ns)
        self._step_ns = int(step_ns)
        self._sequence = 0
        self.episodes_written = 0
        self._out: Output | None = None
        self._done = False
        self.failed: BaseException | None = None  # the write error that stopped this writer, if any

    # -- lifecycle
    def open(self) -> ArchiveWriter:
        if self._out is not None or self._done:
            raise ArchiveError(f"archive writer for {self.path!r} was already opened")
        self._out = Output(self.path, **self._options)
        out = self._out
        try:
            schema = out.schema("ocv2.Episode", "jsonschema", to_json(EPISODE_SCHEMA))
            self._episode_channel = out.channel(EPISODE_TOPIC, "json", schema, {"format_version": str(FORMAT_VERSION)})
            if self.foxglove_frames:
                schema = out.schema("foxglove.RawImage", "jsonschema", to_json(RAW_IMAGE_SCHEMA))
                self._frames_channel = out.channel(FRAMES_TOPIC, "json", schema, {})
        except BaseException as error:
            self._fail(error)
            raise
        return self

    @property
    def partial_path(self) -> str:
        """Where the episodes are while the writer is open (and after it failed)."""
        return self.path + PARTIAL_SUFFIX

    def close(self):
        """Finish the file (summary, footer) and move it to its final name. Safe to call twice.

        A failed writer is not finished: its ``.partial`` holds the episodes written before the error.
        """
        if self._out is not None and not self._done:
            self._done = True
            try:
                self._out.finish()
            except BaseException as error:
                self.failed = error
                raise

    def _fail(self, error: BaseException) -> None:
        self.failed = error
        self._abandon()

    def _abandon(self) -> None:
        """Stop without finishing: the episodes written so far stay in the ``.partial`` (``recover`` makes a file
        of them); a header alone (Ctrl-C or a full disk in the first episode) is removed, as there is nothing to
        recover and a later writer of PATH would refuse it as unfinished."""
        self._done = True
        self._out.abandon()
        if self.episodes_written == 0:
            _unlink_quietly(self._out.partial)

    def __enter__(self) -> ArchiveWriter:
        return self.open()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        elif self._out is not None and not self._done:
            # Interrupted or failed inside the block: not finished, and an existing PATH is not replaced by what
            # would look like a finished archive holding only part of the episodes.
            self._abandon()
        return False

    # -- episodes
    def write_episode(
        self,
        meta: dict | None,
        states: State,
        actions,
        rewards,
        shaped_rewards,
        dones,
        *,
        layout: Layout | str | None = None,
    ) -> int:
        """Append one complete episode; returns its index in the file.

        Args:
            meta: JSON-serialisable metadata (suggested keys: method, iteration, policies, checkpoints,
                seed, env_params -- see ``env_meta``). Tuples come back as lists.
            states: ``ocv2.State`` with a leading axis of T + 1: s_0 (the reset state) ... s_T.
            actions: int[T, N] joint action taken in s_t.
            rewards: float[T] team reward of each transition.
            shaped_rewards: float[T, N].
            dones: bool[T] whether transition t ended the episode.
            layout: the episode's layout (name or ``Layout``); default ``meta['layout']``.

        Raises:
            ArchiveError: the writer is not open, or failed earlier. OSError: writing failed (the
            writer is failed from then on). ValueError/TypeError: inconsistent shapes, a state from
            another kitchen, metadata that is not JSON or uses a reserved key.
        """
        if self.failed is not None:
            kept = self.episodes_written
            raise ArchiveError(
                f"archive writer for {self.path!r} failed earlier ({self.failed}); refusing more episodes. "
                f"The {kept} episode(s) written before are in {self.partial_path!r}: finish them with "
                f"'ocv2 archive recover {self.partial_path}'"
            )
        if self._out is None or self._done:
            raise ArchiveError("write_episode needs an open ArchiveWriter (use it as a context manager)")
        meta = dict(meta or {})
        layout = self._resolve_layout(meta, layout)
        leaves, table, rows, steps, num_agents = _episode_rows(states, actions, rewards, shaped_rewards, dones, layout)
        try:  # the reader refuses deeper records: never write one it cannot read back
            user = boundedjson.loads(to_json(meta))
        except (boundedjson.JSONDepthError, RecursionError):
            raise ArchiveError(f"episode meta nests deeper than {boundedjson.MAX_DEPTH} levels") from None
        rewards32 = np.asarray(rewards, np.float32)
        shaped32 = np.asarray(shaped_rewards, np.float32)
        t0 = self._clock
        record = {
            "format_version": FORMAT_VERSION,
            "episode": self.episodes_written,
            "layout": layout.name,
            "steps": steps,
            "num_agents": num_agents,
            "return": float(rewards32.sum(dtype=np.float64)),
            "shaped_return": [float(v) for v in shaped32.sum(axis=0, dtype=np.float64)],
            "sequence_start": self._sequence,
            "log_time_start": t0,
            "log_time_end": t0 + steps * self._step_ns,
        }
        record.update({k: v for k, v in user.items() if k != "layout"})
        commit = to_json(record)  # fails (NaN return) before anything is written
        frames = self._frames(leaves, layout) if self.foxglove_frames else None

        out = self._out
        try:
            step_channel = out.channel(
                STEP_TOPIC,
                STEP_ENCODING,
                0,
                {
                    "format_version": str(FORMAT_VERSION),
                    "byte_order": "little",
                    "fields": json.dumps(table),
                    "layout": json.dumps(layout_spec(layout)),
                },
            )
            for t in range(steps + 1):
                log_time = t0 + t * self._step_ns
                out.mcap.add_message(step_channel, log_time, rows[t].tobytes(), log_time, self._sequence + t)
                if frames is not None:
                    out.mcap.add_message(
                        self._frames_channel, log_time, _raw_image(frames[t], log_time), log_time, self._sequence + t
                    )
            out.mcap.add_message(
                self._episode_channel, record["log_time_end"], commit, record["log_time_end"], record["episode"]
            )
            out.commit()
        except BaseException as error:  # the MCAP writer's state is unknown now: write nothing more
            self._fail(error)
            raise
        self._clock = t0 + (steps + 1) * self._step_ns
        self._sequence += steps + 1
        self.episodes_written += 1
        return record["episode"]

    def _resolve_layout(self, meta: dict, layout) -> Layout:
        for key in RESERVED_KEYS:
            if key in meta and key != "layout":
                raise ValueError(f"episode metadata key {key!r} is reserved (set by the archive); rename it")
        if layout is None:
            if "layout" not in meta:
                raise ValueError("write_episode needs the layout: pass layout=... or meta['layout']")
            layout = meta["layout"]
        layout = get_layout(layout)
        named = meta.get("layout", layout.name)
        named = named.name if isinstance(named, Layout) else named
        if named != layout.name:
            raise ValueError(f"meta['layout'] is {named!r} but the episode's layout is {layout.name!r}")
        return layout

    def _frames(self, leaves, layout: Layout) -> np.ndarray:
        states = jax.tree_util.tree_unflatten(STATE_TREEDEF, leaves)
        return render_frames(states, layout, tile_size=self.frame_tile_size)


def _episode_rows(states, actions, rewards, shaped_rewards, dones, layout: Layout):
    """Validate one episode and pack it into uint8[T + 1, row_bytes] step payloads."""
    if not isinstance(states, State):
        raise TypeError(f"states must be an ocv2.State with a leading time axis, got {type(states).__name__}")
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(states)]
    actions = np.asarray(actions)
    if actions.ndim != 2:
        raise ValueError(f"actions must be int[T, N], got shape {actions.shape}")
    steps, num_agents = actions.shape
    if steps < 1:
        raise ValueError("an episode needs at least one transition")
    expected_agents = layout.num_agents
    if num_agents != expected_agents:
        raise ValueError(f"actions have {num_agents} agents but layout {layout.name!r} has {expected_agents}")
    if not np.issubdtype(actions.dtype, np.integer) or actions.min() < 0 or actions.max() > np.iinfo(np.int32).max:
        raise ValueError(f"actions must be non-negative integers, got dtype {actions.dtype}")
    expected = {"rewards": (steps,), "shaped_rewards": (steps, num_agents), "dones": (steps,)}
    arrays = {"rewards": np.asarray(rewards), "shaped_rewards": np.asarray(shaped_rewards), "dones": np.asarray(dones)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(f"{name} must have shape {shape} (T={steps}, N={num_agents}), got {arrays[name].shape}")
    if arrays["dones"].dtype != np.bool_:
        raise ValueError(f"dones must be booleans, got dtype {arrays['dones'].dtype}")
    for leaf, name in zip(leaves, STATE_NAMES):
        if leaf.ndim == 0 or leaf.shape[0] != steps + 1:
            raise ValueError(
                f"states.{name} has shape {leaf.shape}: states need a leading axis of T + 1 = {steps + 1} "
                f"(s_0 ... s_T) for {steps} actions"
            )
    grid = leaves[STATE_NAMES.index("grid")]
    if grid.shape[1:3] != (layout.height, layout.width) or not (grid[..., 0] == layout.static_objects).all():
        raise ValueError(
            f"the states' kitchen (grid {grid.shape[1:3]}) is not layout {layout.name!r} "
            f"({layout.height}x{layout.width})"
        )
    table = field_table(leaves, num_agents)
    padded = {  # the final state's message carries a padding transition
        "action": np.concatenate([actions.astype(np.int32), np.full((1, num_agents), -1, np.int32)]),
        "reward": np.concatenate([arrays["rewards"].astype(np.float32), np.zeros(1, np.float32)]),
        "shaped_reward": np.concatenate(
            [arrays["shaped_rewards"].astype(np.float32), np.zeros((1, num_agents), np.float32)]
        ),
        "done": np.concatenate([arrays["dones"], np.zeros(1, bool)]),
    }
    columns = list(leaves) + [padded[name] for name in TRANSITION_FIELDS]
    packed = [
        np.ascontiguousarray(col, dtype=np.dtype(f["dtype"])).reshape(steps + 1, -1).view(np.uint8)
        for col, f in zip(columns, table)
    ]
    return leaves, table, np.concatenate(packed, axis=1), steps, num_agents


def _raw_image(frame: np.ndarray, log_time: int) -> bytes:
    height, width, _ = frame.shape
    return to_json(
        {
            "timestamp": {"sec": log_time // 1_000_000_000, "nsec": log_time % 1_000_000_000},
            "frame_id": "kitchen",
            "width": width,
            "height": height,
            "encoding": "rgb8",
            "step": width * 3,
            "data": base64.b64encode(np.ascontiguousarray(frame, np.uint8).tobytes()).decode("ascii"),
        }
    )
