"""The trajectory archive: whole episodes (states, actions, rewards) in MCAP files.

The only module of the project that imports ``mcap``. Format, crash safety and commands are
documented in ``docs/archive.md``; in short:

* One file holds any number of episodes. Each episode is written as T + 1 ``step`` messages (state
  s_t plus the transition taken from it; the last message carries the final state s_T and a padding
  transition) followed by one ``episode`` message (JSON metadata). The ``episode`` message is the
  commit record: an episode counts only once it is on disk, and steps without one are dropped.
* ``step`` payloads are raw little-endian arrays concatenated in a fixed order; the field table
  (name, dtype, shape) and the layout are in the channel's metadata. Chunks are zstd-compressed.
* ``ArchiveWriter`` writes ``PATH.partial``, flushes a chunk at every episode end, and on close
  (always, even on an exception) finishes the file and renames it to ``PATH``. A writer that is
  killed leaves ``PATH.partial``; ``recover`` (``ocv2 archive recover``) rewrites every complete
  episode of it into a clean file.
* Optionally (off by default) a ``frames`` channel holds each state rendered as a Foxglove
  ``foxglove.RawImage`` (JSON), so the file opens in Foxglove Studio.

Reading never needs the file's summary: ``ArchiveReader`` scans records in file order and so reads
finished and unfinished (``.partial``) files alike.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
import os
import time
from typing import Iterator, NamedTuple, Sequence

import jax
import numpy as np
from mcap.records import Channel, Chunk, Footer, Header, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer

from ocv2.layouts import LAYOUTS, Layout, get_layout
from ocv2.state import Agents, State

__all__ = [
    "ArchiveError", "ArchiveReader", "ArchiveWriter", "Episode", "RecoveryReport", "env_meta", "record_episodes",
    "record_pairs", "recover", "states_as_buffer", "FORMAT_VERSION", "PARTIAL_SUFFIX",
]

PROFILE = "ocv2-archive"  # MCAP header profile: marks an ocv2 archive
FORMAT_VERSION = 1
LIBRARY = f"ocv2-archive/{FORMAT_VERSION}"
PARTIAL_SUFFIX = ".partial"
EPISODE_TOPIC = "episode"
STEP_TOPIC = "step"
FRAMES_TOPIC = "frames"
STEP_ENCODING = "x-ocv2-fields"  # message encoding of ``step``: raw fields, table in channel metadata
MAGIC = b"\x89MCAP0\r\n"

#: Keys the writer sets in every episode's metadata (a caller's ``meta`` must not use them, except
#: ``layout``, which must then name the episode's layout).
RESERVED_KEYS = ("format_version", "episode", "layout", "steps", "num_agents", "return", "shaped_return",
                 "sequence_start", "log_time_start", "log_time_end")

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

_EPISODE_SCHEMA = {
    "title": "ocv2.Episode",
    "description": "Metadata of one archived OvercookedV2 episode (written after its steps: the commit record).",
    "type": "object",
    "properties": {
        "episode": {"type": "integer", "description": "index of the episode in this file"},
        "layout": {"type": "string"},
        "steps": {"type": "integer", "description": "transitions T (the step channel holds T + 1 messages)"},
        "num_agents": {"type": "integer"},
        "return": {"type": "number", "description": "sum of the team reward"},
        "shaped_return": {"type": "array", "items": {"type": "number"}},
        "sequence_start": {"type": "integer"},
        "log_time_start": {"type": "integer"},
        "log_time_end": {"type": "integer"},
    },
    "additionalProperties": True,
}

# foxglove.RawImage as a JSON schema (the well-known schema; Foxglove recognises it by its name).
_RAW_IMAGE_SCHEMA = {
    "title": "foxglove.RawImage",
    "description": "A raw image",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time", "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
        "frame_id": {"type": "string"},
        "width": {"type": "integer", "minimum": 0},
        "height": {"type": "integer", "minimum": 0},
        "encoding": {"type": "string"},
        "step": {"type": "integer", "minimum": 0},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


class ArchiveError(Exception):
    """A file that is not a (readable) ocv2 archive, or a request it cannot satisfy."""


class Episode(NamedTuple):
    """One archived episode of T transitions; arrays are numpy with the dtypes written."""

    meta: dict
    states: State  # [T + 1, ...] s_0 ... s_T (dtypes as ocv2.State: int32 / bool)
    actions: np.ndarray  # int32[T, N] joint action taken in s_t
    rewards: np.ndarray  # float32[T] team reward of transition t
    shaped_rewards: np.ndarray  # float32[T, N]
    dones: np.ndarray  # bool[T] transition t ended the episode


class RecoveryReport(NamedTuple):
    """What ``recover`` kept and dropped."""

    path: str  # the clean file written
    episodes: int  # complete episodes recovered
    transitions: int
    dropped_messages: int  # step/frame messages of episodes that never completed
    source_finished: bool  # the source was a properly finished file (nothing needed recovering)
    tail_error: str | None  # why the scan stopped early (a truncated or corrupt record), if it did


# ---------------------------------------------------------------------------------------------------
# State fields
# ---------------------------------------------------------------------------------------------------

def _state_treedef_and_names():
    dummy = State(agents=Agents(**{f.name: 0 for f in dataclasses.fields(Agents)}),
                  **{f.name: 0 for f in dataclasses.fields(State) if f.name != "agents"})
    leaves, treedef = jax.tree_util.tree_flatten_with_path(dummy)
    names = [jax.tree_util.keystr(path, simple=True, separator=".") for path, _ in leaves]
    return treedef, names


_STATE_TREEDEF, _STATE_NAMES = _state_treedef_and_names()
#: The transition fields after the state fields of every ``step`` message.
_TRANSITION_FIELDS = ("action", "reward", "shaped_reward", "done")


def _field_table(state_leaves: Sequence[np.ndarray], num_agents: int) -> list[dict]:
    """(name, little-endian dtype, per-step shape) of every field of a step message, in order."""
    table = [{"name": "state." + name, "dtype": leaf.dtype.newbyteorder("<").str, "shape": list(leaf.shape[1:])}
             for name, leaf in zip(_STATE_NAMES, state_leaves)]
    table += [
        {"name": "action", "dtype": "<i4", "shape": [num_agents]},
        {"name": "reward", "dtype": "<f4", "shape": []},
        {"name": "shaped_reward", "dtype": "<f4", "shape": [num_agents]},
        {"name": "done", "dtype": "|b1", "shape": []},
    ]
    return table


def _field_sizes(table: list[dict]) -> list[int]:
    return [np.dtype(f["dtype"]).itemsize * math.prod(f["shape"]) for f in table]


# ---------------------------------------------------------------------------------------------------
# Layouts and metadata
# ---------------------------------------------------------------------------------------------------

def _layout_spec(layout: Layout) -> dict:
    return {
        "name": layout.name,
        "map": layout.to_string(),
        "agent_positions": [list(p) for p in layout.agent_positions],
        "num_ingredients": layout.num_ingredients,
        "possible_recipes": [list(r) for r in layout.possible_recipes],
    }


def _layout_from_spec(spec: dict) -> Layout:
    """The built-in layout of that name if it is the same kitchen, else the stored one rebuilt."""
    builtin = LAYOUTS.get(spec["name"])
    if builtin is not None and _layout_spec(builtin) == spec:
        return builtin
    static = Layout.from_string(spec["map"], spec["possible_recipes"], name=spec["name"]).static_objects
    return Layout(static_objects=static, agent_positions=tuple(tuple(p) for p in spec["agent_positions"]),
                  num_ingredients=spec["num_ingredients"],
                  possible_recipes=tuple(tuple(r) for r in spec["possible_recipes"]), name=spec["name"])


def _json_default(value):
    if isinstance(value, (np.generic, np.ndarray, jax.Array)):
        return np.asarray(value).tolist()
    if isinstance(value, (tuple, set, frozenset)):
        return list(value)
    if isinstance(value, Layout):
        return value.name
    raise TypeError(f"episode metadata value {value!r} ({type(value).__name__}) is not JSON-serialisable")


def _to_json(value) -> bytes:
    return json.dumps(value, default=_json_default, allow_nan=False, separators=(",", ":")).encode()


def env_meta(env) -> dict:
    """Episode metadata describing an ``ocv2.make`` environment: ``layout`` and ``env_params``."""
    config = env.config
    params = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name != "layout"}
    return {"layout": config.layout.name, "env_params": json.loads(_to_json(params))}


# ---------------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------------

class _Output:
    """An MCAP file written as ``PATH.partial`` and renamed to ``PATH`` once finished."""

    def __init__(self, path, *, chunk_size: int, compression: str, overwrite: bool, fsync: bool,
                 message_index: bool = True, suffix: str = PARTIAL_SUFFIX):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}")
        self.path = os.fspath(path)
        self.partial = self.path + suffix
        for existing in (self.path, self.partial):
            if os.path.exists(existing) and not overwrite:
                hint = " (an unfinished archive: recover it with 'ocv2 archive recover')" \
                    if existing == self.partial else ""
                raise ArchiveError(f"{existing!r} already exists{hint}; pass overwrite=True to replace it")
        if overwrite and os.path.exists(self.path):
            os.unlink(self.path)
        self._fsync = fsync
        folder = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(folder, exist_ok=True)
        self._file = open(self.partial, "wb")
        try:
            index_types = IndexType.ALL if message_index else IndexType.ALL & ~IndexType.MESSAGE
            self.mcap = Writer(self._file, chunk_size=int(chunk_size), compression=_COMPRESSION[compression],
                               index_types=index_types)
            self.mcap.start(profile=PROFILE, library=LIBRARY)
            self._file.flush()  # the header is on disk: an empty file never looks like a broken archive
        except BaseException:
            self._file.close()
            raise
        self._schemas: dict[tuple, int] = {}
        self._channels: dict[tuple, int] = {}
        self.closed = False

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, data)
        if key not in self._schemas:
            self._schemas[key] = self.mcap.register_schema(name, encoding, data)
        return self._schemas[key]

    def channel(self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]) -> int:
        key = (topic, encoding, schema_id, tuple(sorted(metadata.items())))
        if key not in self._channels:
            self._channels[key] = self.mcap.register_channel(topic, encoding, schema_id, metadata)
        return self._channels[key]

    def commit(self):
        """End the chunk in progress and push everything to the OS (and the disk if ``fsync``)."""
        self.mcap.flush()
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())

    def finish(self):
        """Write the summary and footer, close, and rename ``PATH.partial`` to ``PATH``. Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            self.mcap.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()
        os.replace(self.partial, self.path)


class ArchiveWriter:
    """Write whole episodes to an MCAP archive; a context manager that always finishes the file.

    ::

        with ArchiveWriter("run/archive/xp.mcap") as archive:
            archive.write_episode({"method": "sp", "policies": [0, 1]}, states, actions, rewards, shaped, dones,
                                  layout="cramped_room")

    While open the data goes to ``PATH.partial``; every ``write_episode`` ends with a chunk flush, so
    a killed process loses at most the episode being written (``recover`` rescues the rest). Leaving
    the ``with`` block -- normally or by an exception -- finishes the file (summary, indexes, footer)
    and renames it to ``PATH``. The writer opens and closes its own file.

    Args:
        path: the archive to create (conventionally ``*.mcap``).
        foxglove_frames: also write a ``frames`` channel of rendered states (``foxglove.RawImage``,
            JSON) for Foxglove Studio. Off by default: it makes files ~10x larger and writing slower.
        frame_tile_size: pixels per grid cell of those frames.
        chunk_size: uncompressed bytes after which a chunk is closed inside a long episode.
        compression: 'zstd' (default), 'lz4' or 'none'.
        fsync: also fsync at every episode end (survives power loss, not only a killed process).
        overwrite: replace an existing ``PATH`` / ``PATH.partial`` instead of raising.
        message_index: write MCAP message indexes (default). Without them files are ~40 % smaller and
            this module reads them the same, but indexed readers such as Foxglove's rely on them.
        start_time_ns: log time of the first message (default: now). Messages are ``step_ns`` apart.
    """

    def __init__(self, path, *, foxglove_frames: bool = False, frame_tile_size: int = 16,
                 chunk_size: int = 1 << 20, compression: str = "zstd", fsync: bool = False,
                 overwrite: bool = False, message_index: bool = True, start_time_ns: int | None = None,
                 step_ns: int = 100_000_000):
        self.path = os.fspath(path)
        self.foxglove_frames = bool(foxglove_frames)
        self.frame_tile_size = int(frame_tile_size)
        self._options = dict(chunk_size=chunk_size, compression=compression, overwrite=overwrite, fsync=fsync,
                             message_index=message_index)
        self._clock = time.time_ns() if start_time_ns is None else int(start_time_ns)
        self._step_ns = int(step_ns)
        self._sequence = 0
        self.episodes_written = 0
        self._out: _Output | None = None
        self._done = False

    # -- lifecycle
    def open(self) -> "ArchiveWriter":
        if self._out is not None or self._done:
            raise ArchiveError(f"archive writer for {self.path!r} was already opened")
        self._out = _Output(self.path, **self._options)
        out = self._out
        try:
            schema = out.schema("ocv2.Episode", "jsonschema", _to_json(_EPISODE_SCHEMA))
            self._episode_channel = out.channel(EPISODE_TOPIC, "json", schema,
                                                {"format_version": str(FORMAT_VERSION)})
            if self.foxglove_frames:
                schema = out.schema("foxglove.RawImage", "jsonschema", _to_json(_RAW_IMAGE_SCHEMA))
                self._frames_channel = out.channel(FRAMES_TOPIC, "json", schema, {})
        except BaseException:
            self.close()
            raise
        return self

    def close(self):
        """Finish the file (summary, footer) and move it to its final name. Safe to call twice."""
        if self._out is not None and not self._done:
            self._done = True
            self._out.finish()

    def __enter__(self) -> "ArchiveWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb):
        self.close()
        return False

    # -- episodes
    def write_episode(self, meta: dict | None, states: State, actions, rewards, shaped_rewards, dones, *,
                      layout: Layout | str | None = None) -> int:
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
            ArchiveError: the writer is not open. ValueError/TypeError: inconsistent shapes, a state
            from another kitchen, metadata that is not JSON or uses a reserved key.
        """
        if self._out is None or self._done:
            raise ArchiveError("write_episode needs an open ArchiveWriter (use it as a context manager)")
        meta = dict(meta or {})
        layout = self._resolve_layout(meta, layout)
        leaves, table, rows, steps, num_agents = _episode_rows(states, actions, rewards, shaped_rewards, dones,
                                                               layout)
        user = json.loads(_to_json(meta))
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
        commit = _to_json(record)  # fails (NaN return) before anything is written
        frames = self._frames(leaves, layout) if self.foxglove_frames else None

        out = self._out
        step_channel = out.channel(STEP_TOPIC, STEP_ENCODING, 0, {
            "format_version": str(FORMAT_VERSION),
            "byte_order": "little",
            "fields": json.dumps(table),
            "layout": json.dumps(_layout_spec(layout)),
        })
        try:
            for t in range(steps + 1):
                log_time = t0 + t * self._step_ns
                out.mcap.add_message(step_channel, log_time, rows[t].tobytes(), log_time, self._sequence + t)
                if frames is not None:
                    out.mcap.add_message(self._frames_channel, log_time, _raw_image(frames[t], log_time),
                                         log_time, self._sequence + t)
            out.mcap.add_message(self._episode_channel, record["log_time_end"], commit,
                                 record["log_time_end"], record["episode"])
            out.commit()
        finally:  # even a half-written episode uses up its times: readers drop it as uncommitted
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
        from ocv2.render import render_frames

        states = jax.tree_util.tree_unflatten(_STATE_TREEDEF, leaves)
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
    for leaf, name in zip(leaves, _STATE_NAMES):
        if leaf.ndim == 0 or leaf.shape[0] != steps + 1:
            raise ValueError(
                f"states.{name} has shape {leaf.shape}: states need a leading axis of T + 1 = {steps + 1} "
                f"(s_0 ... s_T) for {steps} actions")
    grid = leaves[_STATE_NAMES.index("grid")]
    if grid.shape[1:3] != (layout.height, layout.width) or not (grid[..., 0] == layout.static_objects).all():
        raise ValueError(f"the states' kitchen (grid {grid.shape[1:3]}) is not layout {layout.name!r} "
                         f"({layout.height}x{layout.width})")
    table = _field_table(leaves, num_agents)
    padded = {  # the final state's message carries a padding transition
        "action": np.concatenate([actions.astype(np.int32), np.full((1, num_agents), -1, np.int32)]),
        "reward": np.concatenate([arrays["rewards"].astype(np.float32), np.zeros(1, np.float32)]),
        "shaped_reward": np.concatenate([arrays["shaped_rewards"].astype(np.float32),
                                         np.zeros((1, num_agents), np.float32)]),
        "done": np.concatenate([arrays["dones"], np.zeros(1, bool)]),
    }
    columns = list(leaves) + [padded[name] for name in _TRANSITION_FIELDS]
    packed = [np.ascontiguousarray(col, dtype=np.dtype(f["dtype"])).reshape(steps + 1, -1).view(np.uint8)
              for col, f in zip(columns, table)]
    return leaves, table, np.concatenate(packed, axis=1), steps, num_agents


def _raw_image(frame: np.ndarray, log_time: int) -> bytes:
    height, width, _ = frame.shape
    return _to_json({
        "timestamp": {"sec": log_time // 1_000_000_000, "nsec": log_time % 1_000_000_000},
        "frame_id": "kitchen",
        "width": width,
        "height": height,
        "encoding": "rgb8",
        "step": width * 3,
        "data": base64.b64encode(np.ascontiguousarray(frame, np.uint8).tobytes()).decode("ascii"),
    })


# ---------------------------------------------------------------------------------------------------
# Scanning (finished and unfinished files alike)
# ---------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class _ScanStatus:
    finished: bool = False  # the footer and closing magic were read
    tail_error: str | None = None  # the record the scan could not read, if any
    orphan_messages: int = 0  # messages of episodes that never committed
    bad_episodes: int = 0  # commit records whose steps did not match (never written by this writer)
    channels: dict = dataclasses.field(default_factory=dict)  # id -> Channel
    schemas: dict = dataclasses.field(default_factory=dict)  # id -> Schema
    header: Header | None = None


class _Group(NamedTuple):
    meta: dict
    commit: Message
    steps: list  # Message, t = 0..T
    others: list  # other messages of the episode (frames), in file order


def _check_file(path: str) -> int:
    if not os.path.exists(path):
        raise ArchiveError(f"no such file: {path!r}")
    if os.path.isdir(path):
        raise ArchiveError(f"{path!r} is a folder, not an archive file")
    size = os.path.getsize(path)
    if size:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
        if head != MAGIC[:len(head)] or len(head) < len(MAGIC):
            raise ArchiveError(f"{path!r} is not an MCAP file (it does not start with the MCAP magic bytes)")
    return size


def _records(path: str, status: _ScanStatus, time_range: tuple[int, int] | None) -> Iterator:
    """Records in file order, chunks opened (or skipped outside ``time_range``); stops at the first bad one."""
    with open(path, "rb") as f:
        reader = iter(StreamReader(f, emit_chunks=True, validate_crcs=True).records)
        while True:
            try:
                record = next(reader)
            except StopIteration:
                return
            except Exception as error:  # truncated / torn / corrupt tail: everything before it counts
                status.tail_error = f"truncated or corrupt record ({type(error).__name__}: {error})"
                return
            if isinstance(record, Chunk):
                if time_range is not None and (record.message_end_time < time_range[0]
                                               or record.message_start_time > time_range[1]):
                    continue
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except Exception as error:
                    status.tail_error = f"corrupt chunk: {type(error).__name__}: {error}"
                    return
                yield from inner
            else:
                if isinstance(record, Footer):
                    status.finished = True
                yield record


def _scan(path: str, status: _ScanStatus, time_range: tuple[int, int] | None = None) -> Iterator[_Group]:
    """Committed episodes of an archive, in file order, with their messages."""
    size = _check_file(path)
    if size == 0:
        status.tail_error = "empty file (the writer died before writing its header)"
        return
    pending: list[Message] = []
    first = True
    for record in _records(path, status, time_range):
        if first:
            first = False
            if not isinstance(record, Header) or record.profile != PROFILE:
                profile = record.profile if isinstance(record, Header) else "?"
                raise ArchiveError(f"{path!r} is an MCAP file but not an ocv2 archive (profile {profile!r}, "
                                   f"expected {PROFILE!r})")
            status.header = record
            continue
        if isinstance(record, Schema):
            status.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            status.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            channel = status.channels.get(record.channel_id)
            if channel is None or channel.topic != EPISODE_TOPIC:
                pending.append(record)
                continue
            meta = json.loads(record.data)
            start = meta["log_time_start"]
            mine = [m for m in pending if m.log_time >= start]
            status.orphan_messages += len(pending) - len(mine)
            pending = []
            steps = [m for m in mine if _topic(status, m) == STEP_TOPIC]
            expected = list(range(meta["sequence_start"], meta["sequence_start"] + meta["steps"] + 1))
            if [m.sequence for m in steps] != expected:
                status.bad_episodes += 1
                continue
            others = [m for m in mine if _topic(status, m) != STEP_TOPIC]
            yield _Group(meta, record, steps, others)
    if pending:
        status.orphan_messages += len(pending)
    if first and status.tail_error is None:
        status.tail_error = "no records"


def _topic(status: _ScanStatus, message: Message) -> str | None:
    channel = status.channels.get(message.channel_id)
    return None if channel is None else channel.topic


def _decode_steps(channel: Channel, steps: Sequence[Message]):
    """(states, actions, rewards, shaped, dones) from the T + 1 step messages of one episode."""
    table = json.loads(channel.metadata["fields"])
    names = [f["name"] for f in table]
    expected = ["state." + n for n in _STATE_NAMES] + list(_TRANSITION_FIELDS)
    if names != expected:
        raise ArchiveError(f"the archive's step fields {names} differ from this ocv2 version's {expected}")
    sizes = _field_sizes(table)
    count = len(steps)
    rows = np.frombuffer(b"".join(m.data for m in steps), dtype=np.uint8)
    if rows.size != count * sum(sizes):
        raise ArchiveError(f"step messages have {rows.size // max(count, 1)} bytes, the field table says {sum(sizes)}")
    rows = rows.reshape(count, sum(sizes))
    columns, offset = {}, 0
    for field, size in zip(table, sizes):
        dtype = np.dtype(field["dtype"])
        column = rows[:, offset:offset + size].copy().view(dtype).reshape([count] + field["shape"])
        columns[field["name"]] = column.astype(dtype.newbyteorder("="))
        offset += size
    states = jax.tree_util.tree_unflatten(_STATE_TREEDEF, [columns["state." + n] for n in _STATE_NAMES])
    return (states, columns["action"][:-1], columns["reward"][:-1], columns["shaped_reward"][:-1],
            columns["done"][:-1])


# ---------------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------------

class ArchiveReader:
    """Read an archive (finished, or an unfinished ``.partial`` whose writer died or still runs).

    Opening scans the file once for the episode index; ``episode(i)`` then decompresses only the
    chunks of episode i. Holds no open file between calls.

    Raises:
        ArchiveError: missing file, not an MCAP file, or an MCAP file that is not an ocv2 archive.
    """

    def __init__(self, path):
        self.path = os.fspath(path)
        self._status = _ScanStatus()
        self._metas: list[dict] = []
        self._step_channels: list[int] = []
        for group in _scan(self.path, self._status):
            self._metas.append(group.meta)
            self._step_channels.append(group.steps[0].channel_id)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def __len__(self) -> int:
        return len(self._metas)

    @property
    def finished(self) -> bool:
        """Whether the file was properly finished (False for a killed or still-running writer's file)."""
        return self._status.finished

    def episodes(self) -> list[dict]:
        """The metadata of every complete episode, in file order."""
        return [dict(m) for m in self._metas]

    def _index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise ArchiveError(f"episode index must be an integer, got {index!r}")
        if not -len(self._metas) <= index < len(self._metas):
            raise ArchiveError(f"episode {index} is out of range: {self.path!r} has {len(self._metas)} "
                               f"complete episode(s) (0..{len(self._metas) - 1})")
        return int(index) % len(self._metas)

    def layout(self, index: int) -> Layout:
        """The layout of episode ``index`` (built-in when it matches by name and map, else rebuilt)."""
        channel = self._status.channels[self._step_channels[self._index(index)]]
        return _layout_from_spec(json.loads(channel.metadata["layout"]))

    def _group(self, index: int) -> _Group:
        index = self._index(index)
        meta = self._metas[index]
        status = _ScanStatus(channels=dict(self._status.channels), schemas=dict(self._status.schemas))
        for group in _scan(self.path, status, (meta["log_time_start"], meta["log_time_end"])):
            if group.meta["episode"] == meta["episode"] and group.meta["log_time_start"] == meta["log_time_start"]:
                return group
        raise ArchiveError(f"episode {index} of {self.path!r} could not be read again (the file changed?)")

    def episode(self, index: int) -> Episode:
        """Episode ``index``: (meta, states [T+1], actions [T, N], rewards [T], shaped [T, N], dones [T])."""
        group = self._group(index)
        return Episode(dict(group.meta), *_decode_steps(self._status.channels[group.steps[0].channel_id], group.steps))

    def iter_episodes(self) -> Iterator[Episode]:
        """Every complete episode in file order (one pass over the file)."""
        status = _ScanStatus()
        for group in _scan(self.path, status):
            yield Episode(dict(group.meta), *_decode_steps(status.channels[group.steps[0].channel_id], group.steps))

    def frames(self, index: int) -> np.ndarray:
        """The Foxglove frames of episode ``index`` decoded to uint8[T + 1, h, w, 3].

        Raises:
            ArchiveError: the archive was written without ``foxglove_frames``.
        """
        group = self._group(index)
        messages = [m for m in group.others if self._status.channels[m.channel_id].topic == FRAMES_TOPIC]
        if not messages:
            raise ArchiveError(f"{self.path!r} has no {FRAMES_TOPIC!r} channel (written without foxglove_frames)")
        images = []
        for m in messages:
            image = json.loads(m.data)
            pixels = np.frombuffer(base64.b64decode(image["data"]), np.uint8)
            images.append(pixels.reshape(image["height"], image["width"], 3))
        return np.stack(images)

    def topics(self) -> list[str]:
        return sorted({c.topic for c in self._status.channels.values()})

    def info(self) -> dict:
        """A summary: episodes, transitions, layouts, policies, methods, returns, file state and size."""
        metas = self._metas
        returns = [m["return"] for m in metas]
        transitions = sum(m["steps"] for m in metas)
        size = os.path.getsize(self.path)

        def count(key_fn):
            counts: dict[str, int] = {}
            for m in metas:
                key = key_fn(m)
                if key is not None:
                    counts[key] = counts.get(key, 0) + 1
            return counts

        per_layout = {}
        for m in metas:
            per_layout.setdefault(m["layout"], []).append(m["return"])
        return {
            "path": self.path,
            "finished": self.finished,
            "size_bytes": size,
            "episodes": len(metas),
            "transitions": transitions,
            "bytes_per_transition": size / transitions if transitions else None,
            "layouts": count(lambda m: m["layout"]),
            "methods": count(lambda m: None if m.get("method") is None else str(m["method"])),
            "policies": count(lambda m: _policies(m)),
            "returns": _stats(returns),
            "returns_by_layout": {name: _stats(values) for name, values in per_layout.items()},
            "topics": self.topics(),
            "foxglove_frames": FRAMES_TOPIC in self.topics(),
            "uncommitted_messages": self._status.orphan_messages,
            "bad_episodes": self._status.bad_episodes,
            "tail_error": None if self.finished else self._status.tail_error,
        }


def _policies(meta: dict) -> str | None:
    policies = meta.get("policies")
    if policies is None:
        return None
    if isinstance(policies, list):
        return " + ".join(str(p) for p in policies)
    return str(policies)


def _stats(values: Sequence[float]) -> dict | None:
    if not values:
        return None
    array = np.asarray(values, np.float64)
    return {"mean": float(array.mean()), "std": float(array.std()), "min": float(array.min()),
            "max": float(array.max())}


# ---------------------------------------------------------------------------------------------------
# Recovery
# ---------------------------------------------------------------------------------------------------

def recover(src, dst, *, overwrite: bool = False) -> RecoveryReport:
    """Copy every complete episode of ``src`` (e.g. a killed writer's ``.partial``) into a clean ``dst``.

    The scan reads records in file order and stops at the first truncated or corrupt one; episodes
    whose commit record precedes it are copied message for message (same channels, metadata, times),
    the rest are dropped and counted. ``dst`` is written as ``dst.recovering`` and renamed when done.

    Raises:
        ArchiveError: ``src`` missing or not an archive; ``dst`` is ``src`` or exists (without overwrite).
    """
    src, dst = os.fspath(src), os.fspath(dst)
    _check_file(src)
    if os.path.abspath(src) == os.path.abspath(dst):
        raise ArchiveError("recover writes a new file: --out must differ from the damaged file")
    status = _ScanStatus()
    groups = _scan(src, status)
    first = next(groups, None)  # raises ArchiveError for a non-archive before dst is created
    # Not dst.partial: that is usually the source itself.
    out = _Output(dst, chunk_size=1 << 20, compression="zstd", overwrite=overwrite, fsync=False,
                  suffix=".recovering")
    episodes = transitions = 0
    ids: dict[int, int] = {}
    try:
        group = first
        while group is not None:
            ordered = sorted(  # steps and frames interleave by time, as written
                [*group.steps, *group.others], key=lambda m: (m.log_time, m.channel_id))
            for message in [*ordered, group.commit]:
                channel_id = _copy_channel(out, status, message.channel_id, ids)
                out.mcap.add_message(channel_id, message.log_time, message.data, message.publish_time,
                                     message.sequence)
            out.commit()
            episodes += 1
            transitions += group.meta["steps"]
            group = next(groups, None)
    finally:
        out.finish()
    return RecoveryReport(dst, episodes, transitions, status.orphan_messages, status.finished,
                          None if status.finished else status.tail_error)


def _copy_channel(out: _Output, status: _ScanStatus, old_id: int, ids: dict[int, int]) -> int:
    if old_id not in ids:
        channel = status.channels[old_id]
        schema_id = 0
        if channel.schema_id:
            schema = status.schemas[channel.schema_id]
            schema_id = out.schema(schema.name, schema.encoding, schema.data)
        ids[old_id] = out.channel(channel.topic, channel.message_encoding, schema_id, dict(channel.metadata))
    return ids[old_id]


# ---------------------------------------------------------------------------------------------------
# Archives as SA reset buffers, and recording policies
# ---------------------------------------------------------------------------------------------------

def states_as_buffer(paths, keep_every: int = 10, layout: Layout | str | None = None) -> State:
    """Archived states as a state-augmentation reset buffer (a batched ``ocv2.State`` of jax arrays).

    Takes s_0, s_k, s_2k, ... (t < T, as SA collection keeps them) of every complete episode of every
    file, in file and episode order. Use it as ``env.reset_state(key, state_buffer=buffer)``, an
    ``ocv2.make(..., initial_state_buffer=buffer)`` or the SA buffer of a training run.

    Args:
        paths: one archive path or a list of them.
        keep_every: k, the stride in time.
        layout: the layout the buffer is for; default the first episode's. Every episode must be of
            this kitchen.

    Raises:
        ArchiveError: no complete episode, or an episode of another layout / shape.
    """
    import jax.numpy as jnp

    from ocv2.config import build_config
    from ocv2.reset import validate_buffer

    if isinstance(keep_every, bool) or not isinstance(keep_every, (int, np.integer)) or keep_every < 1:
        raise ValueError(f"keep_every must be a positive integer, got {keep_every!r}")
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    target = None if layout is None else get_layout(layout)
    parts = []
    for path in paths:
        reader = ArchiveReader(path)
        for index in range(len(reader)):
            episode_layout = reader.layout(index)
            if target is None:
                target = episode_layout
            if not _same_kitchen(episode_layout, target):
                raise ArchiveError(
                    f"{path!r} episode {index} is on layout {episode_layout.name!r} "
                    f"({episode_layout.height}x{episode_layout.width}, {episode_layout.num_agents} agents), not "
                    f"{target.name!r} ({target.height}x{target.width}, {target.num_agents} agents): a reset buffer "
                    "holds states of one kitchen")
        for episode in reader.iter_episodes():
            steps = episode.meta["steps"]
            parts.append(jax.tree.map(lambda x: x[0:steps:keep_every], episode.states))
    if not parts:
        raise ArchiveError(f"no complete episode in {', '.join(map(repr, map(os.fspath, paths)))}")
    buffer = jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs)), *parts)
    try:
        validate_buffer(build_config(target), buffer)
    except (TypeError, ValueError) as error:
        raise ArchiveError(f"archived states do not fit layout {target.name!r}: {error}") from None
    return buffer


def _same_kitchen(a: Layout, b: Layout) -> bool:
    return (a.static_objects.shape == b.static_objects.shape and (a.static_objects == b.static_objects).all()
            and a.num_agents == b.num_agents and a.num_ingredients == b.num_ingredients)


def record_episodes(writer: ArchiveWriter, env, recorded, meta: dict | None = None, first_episode: int = 0) -> list[int]:
    """Write the E episodes of one pair's ``population.record.Recorded`` (no leading pair axis).

    Each episode's metadata is ``env_meta(env)`` + ``meta`` + ``{"pair_episode": first_episode + e}``.
    Returns the archive indices.
    """
    host = jax.device_get(recorded)
    base = {**env_meta(env), **(meta or {})}
    indices = []
    for e in range(np.shape(host.actions)[0]):
        states = jax.tree.map(lambda x: x[e], host.states)
        indices.append(writer.write_episode({**base, "pair_episode": first_episode + e}, states, host.actions[e], host.rewards[e],
                                            host.shaped_rewards[e], host.dones[e], layout=env.layout))
    return indices


def record_pairs(writer: ArchiveWriter, apply, hidden_size: int, env, params_a, params_b, keys, episodes: int,
                 metas: Sequence[dict]) -> list[int]:
    """P pairs play ``episodes`` episodes each (``population.record``) and every episode is archived.

    ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), ``keys`` is [P], ``metas``
    one dict per pair (e.g. ``{"method": "xp", "policies": [i, j], "seed": s}``). Pair p's episodes
    are exactly those ``play_episodes`` would play with ``keys[p]``. Returns the archive indices.
    """
    from population.record import jitted_play_recorded_pairs

    if len(metas) != np.shape(keys)[0]:
        raise ValueError(f"metas has {len(metas)} entries for {np.shape(keys)[0]} pairs")
    recorded = jitted_play_recorded_pairs(apply, hidden_size, env, episodes)(params_a, params_b, keys)
    recorded = jax.device_get(recorded)
    indices = []
    for p, meta in enumerate(metas):
        indices += record_episodes(writer, env, jax.tree.map(lambda x: x[p], recorded), meta)
    return indices
