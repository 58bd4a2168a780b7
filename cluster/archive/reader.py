"""Reading archives record by record: finished, unfinished (``.partial``) and damaged files alike.

Reading never needs the file's summary: records are read in file order. A chunk that fails to
decompress or to match its CRC is skipped with a warning and reading goes on after it; bytes that do
not frame a record (a corrupt record length) are skipped up to the next chunk that checks out. A
chunk whose header times (not under the CRC) disagree with its messages' log times is read, with a
warning, and never passed over by time. A torn tail (a killed writer) simply ends the scan. Commit records and step-channel metadata that do
not follow the format (crafted or foreign files) are an ``ArchiveError`` naming file, episode and key.
"""

from __future__ import annotations

import base64
import dataclasses
import io
import os
import stat
import struct
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import jax
import numpy as np

from cluster.archive.format import (
    EPISODE_TOPIC,
    FORMAT_VERSION,
    FRAMES_TOPIC,
    MAGIC,
    MAX_CHUNK_BYTES,
    MCAP_AVAILABLE,
    PROFILE,
    STATE_NAMES,
    STATE_TREEDEF,
    STEP_TOPIC,
    TRANSITION_DTYPES,
    TRANSITION_FIELDS,
    ArchiveError,
    Episode,
    field_sizes,
    layout_from_spec,
    require_mcap,
)
from ocv2 import boundedjson
from ocv2.config import build_config
from ocv2.layouts import Layout
from ocv2.reset import validate_buffer

if MCAP_AVAILABLE:  # without it, reading raises require_mcap's error (format.py)
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, Header, Message, Schema
    from mcap.stream_reader import breakup_chunk

#: Longest episode (transitions) a commit record may name; beyond it the record is crafted.
MAX_STEPS = 1 << 31
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, content length
_CHUNK_HEAD = struct.Struct("<QQQII")  # start time, end time, uncompressed size, crc, compression length
_FOOTER_BYTES = _RECORD_HEAD.size + 20  # opcode, length, summary start, summary offset start, crc
_KNOWN_OPCODES = {int(op) for op in Opcode} if MCAP_AVAILABLE else set()
_RESYNC_BLOCK = 1 << 20  # bytes read at a time while looking for the next valid chunk


@dataclasses.dataclass
class ScanStatus:
    finished: bool = False  # the footer and closing magic were read
    tail_error: str | None = None  # why the scan stopped before a footer, if it did
    orphan_messages: int = 0  # messages of episodes that never committed (or whose commit was lost)
    bad_episodes: int = 0  # commit records whose step messages are not all there (a skipped chunk)
    warnings: list = dataclasses.field(default_factory=list)  # skipped chunks and records, lost episodes
    channels: dict = dataclasses.field(default_factory=dict)  # id -> Channel
    schemas: dict = dataclasses.field(default_factory=dict)  # id -> Schema
    header: Header | None = None
    # byte offsets of chunks whose header times do not match their messages: never skipped by time
    untrusted_times: set = dataclasses.field(default_factory=set)


class Group(NamedTuple):
    meta: dict
    commit: Message
    steps: list  # Message, t = 0..T
    others: list  # other messages of the episode (frames), in file order


def check_file(path: str) -> int:
    require_mcap()  # every read starts here (scan, recover, ArchiveReader)
    if not os.path.exists(path):
        raise ArchiveError(f"no such file: {path!r}")
    if os.path.isdir(path):
        raise ArchiveError(f"{path!r} is a folder, not an archive file")
    info = os.stat(path)
    if not stat.S_ISREG(info.st_mode):  # a pipe would block the read, a device has no size
        raise ArchiveError(f"{path!r} is not a regular file (a pipe, socket or device); give an archive file")
    size = info.st_size
    if size:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
        if head != MAGIC[: len(head)] or len(head) < len(MAGIC):
            raise ArchiveError(f"{path!r} is not an MCAP file (it does not start with the MCAP magic bytes)")
    return size


# ---------------------------------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------------------------------


class _FileBytes:
    """An open file indexed like bytes, read on demand with ``pread``.

    Not an mmap: a file truncated under a mapping (a failed writer cutting its ``.partial`` back)
    would kill the reading process with SIGBUS. The size is fixed at opening; a file that shrinks
    while it is read gives short reads, which end the scan like a torn tail.
    """

    def __init__(self, file):
        self._fd = file.fileno()
        self._size = os.fstat(self._fd).st_size

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, index):
        if isinstance(index, slice):
            start, stop, _ = index.indices(self._size)
            return os.pread(self._fd, stop - start, start) if stop > start else b""
        return os.pread(self._fd, 1, index)[0]


def _parse(opcode: int, content: bytes):
    stream = ReadDataStream(io.BytesIO(content))
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(content))
    return {Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel}[opcode].read(stream)


def _chunk_at(data, offset: int, size: int) -> tuple[Chunk, list, int] | None:
    """The chunk record at ``offset`` and its records, if one is there whole and checks out; else None."""
    if offset + _RECORD_HEAD.size + _CHUNK_HEAD.size > size or data[offset] != Opcode.CHUNK:
        return None
    _, length = _RECORD_HEAD.unpack(data[offset : offset + _RECORD_HEAD.size])
    end = offset + _RECORD_HEAD.size + length
    if end > size:
        return None
    start = offset + _RECORD_HEAD.size
    *_, uncompressed, _, name_length = _CHUNK_HEAD.unpack(data[start : start + _CHUNK_HEAD.size])
    if name_length > 4 or uncompressed > MAX_CHUNK_BYTES:
        return None
    name_end = start + _CHUNK_HEAD.size + name_length
    if data[start + _CHUNK_HEAD.size : name_end] not in (b"", b"zstd", b"lz4"):
        return None
    if name_end + 8 > end or struct.unpack("<Q", data[name_end : name_end + 8])[0] != end - name_end - 8:
        return None
    try:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[start:end])))
        records = _chunk_records(chunk)
        return None if records is None else (chunk, records, end)
    except Exception:  # noqa: BLE001 -- any failure to decode means: not a whole, valid chunk here
        return None


def _chunk_records(chunk: Chunk) -> list | None:
    """The records of a chunk decompressed within its claimed size (``_decompressed``), CRC checked; None when it
    does not decompress to that size. mcap's parser reads the already decompressed copy."""
    plain = _decompressed(chunk)
    if plain is None:
        return None
    return breakup_chunk(dataclasses.replace(chunk, compression="", data=plain), validate_crc=True)


def _decompressed(chunk: Chunk) -> bytes | None:
    """A chunk's records, decompressed to at most the size its header claims (checked against MAX_CHUNK_BYTES):
    a frame that says more in its own header, or holds more than it says, is not decompressed past that size
    (mcap's own reader would take the frame's word: a 20 KB file could ask for gigabytes). None when the
    decompressed size is not the claimed one."""
    limit = chunk.uncompressed_size
    if chunk.compression == "zstd":
        import zstandard

        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)) as reader:
            plain = reader.read(limit + 1)
    elif chunk.compression == "lz4":
        import lz4.frame

        plain = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=limit + 1)
    else:
        plain = chunk.data
    return plain if len(plain) == limit else None


def _resync(data, offset: int, size: int):
    """The next whole, valid chunk after ``offset`` (None if there is none: a torn tail).

    Every chunk opcode byte is a candidate; almost all fail the header checks of ``_chunk_at`` at
    once, and the CRC settles the rest.
    """
    opcode = bytes([Opcode.CHUNK])
    block_start = offset + 1
    while block_start < size:
        block = data[block_start : block_start + _RESYNC_BLOCK]
        if not block:
            return None
        hit = block.find(opcode)
        while hit >= 0:
            found = _chunk_at(data, block_start + hit, size)
            if found is not None:
                return block_start + hit, found
            hit = block.find(opcode, hit + 1)
        block_start += len(block)
    return None


def _summary_definitions(data, size: int, status: ScanStatus) -> None:
    """Schemas and channels from a finished file's summary: messages keep their channel even when the
    chunk that first defined it is the one that was skipped."""
    try:
        _read_summary_definitions(data, size, status)
    except (struct.error, IndexError):  # a file that shrank meanwhile: no fallback definitions
        pass


def _read_summary_definitions(data, size: int, status: ScanStatus) -> None:
    footer = size - len(MAGIC) - _FOOTER_BYTES
    if footer <= len(MAGIC) or data[size - len(MAGIC) : size] != MAGIC or data[footer] != Opcode.FOOTER:
        return
    summary_start = struct.unpack("<Q", data[footer + _RECORD_HEAD.size : footer + _RECORD_HEAD.size + 8])[0]
    offset = summary_start if len(MAGIC) <= summary_start < footer else footer
    while offset + _RECORD_HEAD.size <= footer:
        opcode, length = _RECORD_HEAD.unpack(data[offset : offset + _RECORD_HEAD.size])
        end = offset + _RECORD_HEAD.size + length
        if end > footer:
            return
        if opcode not in (Opcode.SCHEMA, Opcode.CHANNEL):
            return  # the summary lists schemas and channels first; chunk indexes and the rest follow
        try:
            record = _parse(opcode, data[offset + _RECORD_HEAD.size : end])
        except Exception:  # noqa: BLE001 -- a damaged summary only means no fallback definitions
            return
        (status.schemas if opcode == Opcode.SCHEMA else status.channels).setdefault(record.id, record)
        offset = end


def _records(path: str, status: ScanStatus, time_range: tuple[int, int] | None) -> Iterator:
    """Records in file order, chunks opened (or passed over outside ``time_range``).

    Corrupt chunks and records are skipped with a warning in ``status.warnings``; the scan ends at
    the footer or at a tail that holds no further valid chunk.
    """
    with open(path, "rb") as f:
        data = _FileBytes(f)
        size = len(data)
        fallback = ScanStatus()
        _summary_definitions(data, size, fallback)
        offset = len(MAGIC)
        try:
            while offset < size:
                if offset + _RECORD_HEAD.size > size:
                    status.tail_error = f"truncated record at byte {offset} (the file ends inside it)"
                    return
                opcode, length = _RECORD_HEAD.unpack(data[offset : offset + _RECORD_HEAD.size])
                end = offset + _RECORD_HEAD.size + length
                if opcode not in _KNOWN_OPCODES or end > size:
                    found = _resync(data, offset, size)
                    what = (
                        f"unknown record type {opcode:#x}"
                        if opcode not in _KNOWN_OPCODES
                        else f"record of {length} bytes that runs past the end of the file"
                    )
                    if found is None:
                        status.tail_error = f"truncated or corrupt record at byte {offset} ({what})"
                        return
                    position, _ = found
                    status.warnings.append(f"skipped bytes {offset}..{position} (corrupt: {what} at byte {offset})")
                    offset = position
                    continue
                if opcode == Opcode.CHUNK:
                    if (
                        time_range is not None
                        and offset not in status.untrusted_times
                        and _outside(data, offset, size, time_range)
                    ):
                        offset = end  # another episode's chunk: not even decompressed
                        continue
                    found = _chunk_at(data, offset, size)
                    if found is None:
                        status.warnings.append(f"skipped corrupt {_describe_chunk(data, offset, end)}")
                    else:
                        _check_chunk_times(offset, *found[:2], status)
                        for record in found[1]:
                            _learn(record, status, fallback)
                            yield record
                elif opcode == Opcode.FOOTER:
                    status.finished = True
                    return
                elif opcode in (Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                    try:
                        record = _parse(opcode, data[offset + _RECORD_HEAD.size : end])
                    except Exception as error:  # noqa: BLE001 -- mcap raises assorted errors on garbage
                        status.warnings.append(
                            f"skipped corrupt {Opcode(opcode).name.lower()} record at byte "
                            f"{offset} ({type(error).__name__}: {error})"
                        )
                    else:
                        _learn(record, status, fallback)
                        yield record
                offset = end  # indexes, statistics and the like: not needed to read episodes
        except (struct.error, IndexError):  # short reads: the file shrank under the reader
            status.tail_error = f"the file ended at byte {offset} while it was read (truncated meanwhile)"
            return
        if not status.finished:
            status.tail_error = status.tail_error or "the file ends without a footer"


def _check_chunk_times(offset: int, chunk: Chunk, records: list, status: ScanStatus) -> None:
    """Compare a chunk header's message time range, which its CRC does not cover, with its messages'
    log times (the writer stores their exact minimum and maximum). A mismatch is damage to the header:
    the messages passed the CRC and are read, but the header cannot be trusted to skip the chunk by time."""
    times = [r.log_time for r in records if isinstance(r, Message)]
    if not times:
        return
    first, last = min(times), max(times)
    if (chunk.message_start_time, chunk.message_end_time) != (first, last):
        status.untrusted_times.add(offset)
        status.warnings.append(
            f"chunk at byte {offset}: its header gives message log times {chunk.message_start_time}.."
            f"{chunk.message_end_time} but its {len(times)} messages span {first}..{last} (the header is "
            "damaged; its messages passed the CRC check and are read; 'ocv2 archive recover' writes a "
            "file with correct headers)"
        )


def _outside(data, offset: int, size: int, time_range: tuple[int, int]) -> bool:
    if offset + _RECORD_HEAD.size + _CHUNK_HEAD.size > size:
        return False
    head = offset + _RECORD_HEAD.size
    start, end, *_ = _CHUNK_HEAD.unpack(data[head : head + _CHUNK_HEAD.size])
    return end < time_range[0] or start > time_range[1]


def _describe_chunk(data, offset: int, end: int) -> str:
    """Which chunk failed (byte offset, time range when readable) and why, for the warning."""
    name = f"chunk at byte {offset}"
    try:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[offset + _RECORD_HEAD.size : end])))
        name = f"{name} (messages at log times {chunk.message_start_time}..{chunk.message_end_time})"
        if chunk.uncompressed_size > MAX_CHUNK_BYTES:
            return f"{name}: it claims {chunk.uncompressed_size} bytes uncompressed (at most {MAX_CHUNK_BYTES})"
        if _chunk_records(chunk) is None:  # bounded here too: this is the path every refused chunk takes
            return f"{name}: it does not decompress to the {chunk.uncompressed_size} bytes it claims"
    except Exception as error:  # noqa: BLE001 -- the reason is only reported
        return f"{name}: {type(error).__name__}: {error}"
    return f"{name}: its header is malformed"


def _learn(record, status: ScanStatus, fallback: ScanStatus) -> None:
    """Keep schema and channel definitions; a message on a channel defined only in the summary gets it."""
    if isinstance(record, Schema):
        status.schemas.setdefault(record.id, record)
    elif isinstance(record, Channel):
        status.channels.setdefault(record.id, record)
    elif isinstance(record, Message) and record.channel_id not in status.channels:
        channel = fallback.channels.get(record.channel_id)
        if channel is not None:
            status.channels[channel.id] = channel
            if channel.schema_id in fallback.schemas:
                status.schemas.setdefault(channel.schema_id, fallback.schemas[channel.schema_id])


# ---------------------------------------------------------------------------------------------------
# Episodes
# ---------------------------------------------------------------------------------------------------

_COMMIT_KEYS = {
    "format_version": int,
    "episode": int,
    "layout": str,
    "steps": int,
    "num_agents": int,
    "return": (int, float),
    "shaped_return": list,
    "sequence_start": int,
    "log_time_start": int,
    "log_time_end": int,
}


def _commit_meta(path: str, message: Message) -> dict:
    """A commit record's metadata, checked before anything is sized from it."""
    where = f"{path!r}: the episode record at log time {message.log_time}"
    try:
        meta = boundedjson.loads(message.data)
    except (ValueError, UnicodeDecodeError) as error:
        raise ArchiveError(f"{where} is not JSON ({error})") from None
    if not isinstance(meta, dict):
        raise ArchiveError(f"{where} is a JSON {type(meta).__name__}, not an object")
    if isinstance(meta.get("episode"), int):
        where = f"{path!r}: episode {meta['episode']}"
    for key, kind in _COMMIT_KEYS.items():
        if key not in meta:
            raise ArchiveError(f"{where}: the episode record has no {key!r}")
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ArchiveError(
                f"{where}: key {key!r} is {value!r}, not of type "
                f"{kind.__name__ if isinstance(kind, type) else 'number'}"
            )
    if meta["format_version"] != FORMAT_VERSION:  # a later format may reuse these keys with other meanings
        raise ArchiveError(
            f"{where}: format_version {meta['format_version']}; this ocv2 reads version {FORMAT_VERSION} "
            "(read it with the ocv2 that wrote it)"
        )
    if not 1 <= meta["steps"] <= MAX_STEPS:
        raise ArchiveError(f"{where}: key 'steps' is {meta['steps']}, not a transition count in 1..{MAX_STEPS}")
    if not 1 <= meta["num_agents"] <= 64:
        raise ArchiveError(f"{where}: key 'num_agents' is {meta['num_agents']}, not an agent count in 1..64")
    if len(meta["shaped_return"]) != meta["num_agents"]:
        raise ArchiveError(
            f"{where}: key 'shaped_return' has {len(meta['shaped_return'])} values for {meta['num_agents']} agents"
        )
    return meta


#: The most bytes a file can hold without a complete header when its writer died while writing that header (the
#: magic and one header record of ocv2's profile and library names; writers flush it before anything else).
HEADER_ROOM = len(MAGIC) + 256


def scan(path: str, status: ScanStatus, time_range: tuple[int, int] | None = None) -> Iterator[Group]:
    """Committed episodes of an archive, in file order, with their messages."""
    size = check_file(path)
    if size == 0:
        status.tail_error = "empty file (the writer died before writing its header)"
        return
    pending: list[Message] = []
    first = True
    previous = -1  # index of the last episode yielded: a gap means episodes were lost
    for record in _records(path, status, time_range):
        if first:
            first = False
            if not isinstance(record, Header) or record.profile != PROFILE:
                profile = record.profile if isinstance(record, Header) else "?"
                raise ArchiveError(
                    f"{path!r} is an MCAP file but not an ocv2 archive (profile {profile!r}, expected {PROFILE!r})"
                )
            status.header = record
            continue
        if not isinstance(record, Message):
            continue
        channel = status.channels.get(record.channel_id)
        if channel is None or channel.topic != EPISODE_TOPIC:
            pending.append(record)
            continue
        meta = _commit_meta(path, record)
        start = meta["log_time_start"]
        mine = [m for m in pending if m.log_time >= start]
        status.orphan_messages += len(pending) - len(mine)
        pending = []
        steps = [m for m in mine if _topic(status, m) == STEP_TOPIC]
        first_sequence = meta["sequence_start"]
        if len(steps) != meta["steps"] + 1 or any(m.sequence != first_sequence + t for t, m in enumerate(steps)):
            status.bad_episodes += 1
            status.warnings.append(
                f"episode {meta['episode']}: {len(steps)} of its {meta['steps'] + 1} step "
                "messages are readable; skipped"
            )
            previous = max(previous, meta["episode"])  # reported here, not again as missing
            continue
        if time_range is None:
            if meta["episode"] > previous + 1:
                lost = (
                    f"episode {previous + 1}"
                    if meta["episode"] == previous + 2
                    else f"episodes {previous + 1}..{meta['episode'] - 1}"
                )
                status.warnings.append(
                    f"{lost} missing (in a skipped part of this file, or of the file it was recovered from)"
                )
            previous = meta["episode"]
        others = [m for m in mine if _topic(status, m) != STEP_TOPIC]
        yield Group(meta, record, steps, others)
    if pending:
        status.orphan_messages += len(pending)
    if first and size > HEADER_ROOM:  # no header where a writer puts one first: not an archive, not a torn one
        raise ArchiveError(
            f"{path!r} is not an ocv2 archive: no readable header record in its {size} bytes"
            + (f" ({status.tail_error})" if status.tail_error else "")
        )
    if first and status.tail_error is None:
        status.tail_error = "no records"


def _topic(status: ScanStatus, message: Message) -> str | None:
    channel = status.channels.get(message.channel_id)
    return None if channel is None else channel.topic


def _step_table(path: str, meta: dict, channel: Channel) -> list[dict]:
    """The step channel's field table, checked: known names, plain numeric dtypes, sane shapes."""
    where = f"{path!r}: episode {meta['episode']}: step channel metadata"
    try:
        table = boundedjson.loads(channel.metadata["fields"])
    except KeyError:
        raise ArchiveError(f"{where} has no 'fields'") from None
    except ValueError as error:
        raise ArchiveError(f"{where} key 'fields' is not JSON ({error})") from None
    if not isinstance(table, list) or not all(
        isinstance(f, dict) and {"name", "dtype", "shape"} <= set(f) for f in table
    ):
        raise ArchiveError(f"{where} key 'fields' is not a list of {{name, dtype, shape}} objects")
    names = [f["name"] for f in table]
    expected = ["state." + n for n in STATE_NAMES] + list(TRANSITION_FIELDS)
    if names != expected:
        raise ArchiveError(f"{where}: the archive's step fields {names} differ from this ocv2 version's {expected}")
    if channel.metadata.get("byte_order", "little") != "little":
        raise ArchiveError(f"{where}: byte_order {channel.metadata['byte_order']!r}; ocv2 writes and reads 'little'")
    for field in table:
        try:
            dtype = np.dtype(field["dtype"])
        except (TypeError, ValueError):
            dtype = None
        name = field["name"]
        wanted = TRANSITION_DTYPES.get(name)
        if wanted is not None and field["dtype"] != wanted:
            raise ArchiveError(f"{where} 'fields': {name} has dtype {field['dtype']!r}, not {wanted!r}")
        plain = dtype is not None and dtype.kind in "biu" and dtype.itemsize <= 8  # ocv2.State: ints, bools
        if wanted is None and not plain:
            raise ArchiveError(f"{where} 'fields': {name} has dtype {field['dtype']!r}, not an integer or boolean one")
        shape = field["shape"]
        if (
            not isinstance(shape, list)
            or len(shape) > 4
            or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= 4096 for n in shape)
        ):
            raise ArchiveError(f"{where} 'fields': {field['name']} has shape {shape!r}, not a list of sizes")
    return table


def _channel_layout(path: str, meta: dict, channel: Channel) -> Layout:
    where = f"{path!r}: episode {meta['episode']}: step channel metadata key 'layout'"
    try:
        spec = boundedjson.loads(channel.metadata["layout"])
        return layout_from_spec(spec)
    except KeyError as error:
        raise ArchiveError(f"{where} is missing (or lacks {error})") from None
    except (ValueError, TypeError, AttributeError) as error:
        raise ArchiveError(f"{where} is not a valid layout ({error})") from None


def decode_steps(path: str, meta: dict, channel: Channel, steps: Sequence[Message]):
    """(states, actions, rewards, shaped, dones) from the T + 1 step messages of one episode."""
    table = _step_table(path, meta, channel)
    sizes = field_sizes(table)
    count, width = len(steps), sum(sizes)
    where = f"{path!r}: episode {meta['episode']}"
    bad = [t for t, m in enumerate(steps) if len(m.data) != width]
    if bad:  # checked per message before joining: nothing is allocated from a crafted size
        raise ArchiveError(
            f"{where}: step message {bad[0]} has {len(steps[bad[0]].data)} bytes, the field table says {width}"
        )
    rows = np.frombuffer(b"".join(m.data for m in steps), dtype=np.uint8).reshape(count, width)
    columns, offset = {}, 0
    for field, size in zip(table, sizes):
        dtype = np.dtype(field["dtype"])
        column = rows[:, offset : offset + size].copy().view(dtype).reshape([count] + field["shape"])
        columns[field["name"]] = column.astype(dtype.newbyteorder("="))
        offset += size
    agents = meta["num_agents"]
    for name, shape in {"action": (agents,), "reward": (), "shaped_reward": (agents,), "done": ()}.items():
        if columns[name].shape[1:] != shape:
            raise ArchiveError(
                f"{where}: field {name!r} has per-step shape {list(columns[name].shape[1:])}, "
                f"expected {list(shape)} for {agents} agents"
            )
    states = jax.tree_util.tree_unflatten(STATE_TREEDEF, [columns["state." + n] for n in STATE_NAMES])
    layout = _channel_layout(path, meta, channel)
    try:
        validate_buffer(build_config(layout), states)
    except (TypeError, ValueError) as error:
        raise ArchiveError(f"{where}: the stored states do not fit layout {layout.name!r}: {error}") from None
    return (states, columns["action"][:-1], columns["reward"][:-1], columns["shaped_reward"][:-1], columns["done"][:-1])


# ---------------------------------------------------------------------------------------------------
# The reader
# ---------------------------------------------------------------------------------------------------


class ArchiveReader:
    """Read an archive (finished, or an unfinished ``.partial`` whose writer died or still runs).

    Opening scans the file once for the episode index; ``episode(i)`` then decompresses only the
    chunks of episode i. Holds no open file between calls. ``warnings`` lists what a damaged file
    lost: skipped chunks (by byte offset and time range) and the episodes that went with them.

    Raises:
        ArchiveError: missing file, not an MCAP file, an MCAP file that is not an ocv2 archive, or
            an episode record that does not follow the format.
    """

    def __init__(self, path):
        self.path = os.fspath(path)
        self._status = ScanStatus()
        self._metas: list[dict] = []
        self._step_channels: list[int] = []
        for group in scan(self.path, self._status):
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

    @property
    def has_header(self) -> bool:
        """Whether the file's ocv2 header record was read: False for an empty file, or one whose writer was killed
        inside its first few bytes (nothing in it says it is an archive, and it holds nothing to recover)."""
        return self._status.header is not None

    @property
    def warnings(self) -> list[str]:
        """What could not be read: skipped corrupt chunks or records, and episodes lost with them."""
        return list(self._status.warnings)

    def episodes(self) -> list[dict]:
        """The metadata of every complete episode, in file order."""
        return [dict(m) for m in self._metas]

    def position(self, episode: int) -> int:
        """Where the episode whose stored number (``meta["episode"]``, what ``info`` lists) is ``episode``
        sits among ``episodes()``: the index ``episode()``, ``layout()`` and ``frames()`` take. The two
        differ once a damaged part of the file lost episodes.

        Raises:
            ArchiveError: no complete episode has that number (one line, listing the numbers there are).
        """
        if isinstance(episode, bool) or not isinstance(episode, (int, np.integer)):
            raise ArchiveError(f"episode number must be an integer, got {episode!r}")
        for index, meta in enumerate(self._metas):
            if meta["episode"] == episode:
                return index
        lost = " (episodes lost to damage are listed in the warnings)" if self._status.warnings else ""
        raise ArchiveError(
            f"{self.path!r} has no episode {episode}; its complete episodes are "
            f"{_number_ranges([m['episode'] for m in self._metas]) or 'none'}{lost}"
        )

    def _index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise ArchiveError(f"episode position must be an integer, got {index!r}")
        if not -len(self._metas) <= index < len(self._metas):
            raise ArchiveError(
                f"episode position {index} is out of range: {self.path!r} has {len(self._metas)} "
                f"complete episode(s) (positions 0..{len(self._metas) - 1}; position(N) finds "
                "stored episode number N)"
            )
        return int(index) % len(self._metas)

    def layout(self, index: int) -> Layout:
        """The layout of episode ``index`` (built-in when it matches by name and map, else rebuilt)."""
        index = self._index(index)
        channel = self._status.channels[self._step_channels[index]]
        return _channel_layout(self.path, self._metas[index], channel)

    def _group(self, index: int) -> Group:
        index = self._index(index)
        meta = self._metas[index]
        status = ScanStatus(
            channels=dict(self._status.channels),
            schemas=dict(self._status.schemas),
            untrusted_times=set(self._status.untrusted_times),
        )
        for group in scan(self.path, status, (meta["log_time_start"], meta["log_time_end"])):
            if group.meta["episode"] == meta["episode"] and group.meta["log_time_start"] == meta["log_time_start"]:
                return group
        raise ArchiveError(f"episode {meta['episode']} of {self.path!r} could not be read again (the file changed?)")

    def episode(self, index: int) -> Episode:
        """Episode ``index``: (meta, states [T+1], actions [T, N], rewards [T], shaped [T, N], dones [T])."""
        group = self._group(index)
        channel = self._status.channels[group.steps[0].channel_id]
        return Episode(dict(group.meta), *decode_steps(self.path, group.meta, channel, group.steps))

    def iter_episodes(self) -> Iterator[Episode]:
        """Every complete episode in file order (one pass over the file)."""
        status = ScanStatus()
        for group in scan(self.path, status):
            channel = status.channels[group.steps[0].channel_id]
            yield Episode(dict(group.meta), *decode_steps(self.path, group.meta, channel, group.steps))

    def frames(self, index: int) -> np.ndarray:
        """The Foxglove frames of episode ``index`` decoded to uint8[T + 1, h, w, 3].

        Raises:
            ArchiveError: the archive was written without ``foxglove_frames``, or a frame is malformed.
        """
        group = self._group(index)
        messages = [m for m in group.others if self._status.channels[m.channel_id].topic == FRAMES_TOPIC]
        if not messages:
            raise ArchiveError(f"{self.path!r} has no {FRAMES_TOPIC!r} channel (written without foxglove_frames)")
        images = []
        for t, m in enumerate(messages):
            try:
                image = boundedjson.loads(m.data)
                pixels = np.frombuffer(base64.b64decode(image["data"]), np.uint8)
                images.append(pixels.reshape(image["height"], image["width"], 3))
            except (ValueError, TypeError, KeyError) as error:
                raise ArchiveError(
                    f"{self.path!r}: episode {group.meta['episode']}: frame {t} is not an rgb8 "
                    f"foxglove.RawImage ({type(error).__name__}: {error})"
                ) from None
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
            "warnings": self.warnings,
            "tail_error": None if self.finished else self._status.tail_error,
        }


def _number_ranges(numbers: Sequence[int]) -> str:
    """``0, 2..5, 9`` for [0, 2, 3, 4, 5, 9] (file order kept)."""
    runs: list[list[int]] = []
    for n in numbers:
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}..{b}" for a, b in runs)


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
    return {
        "mean": float(array.mean()),
        "std": float(array.std()),
        "min": float(array.min()),
        "max": float(array.max()),
    }
