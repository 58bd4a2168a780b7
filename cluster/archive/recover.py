"""``recover``: copy every complete episode of a damaged or unfinished archive into a clean file."""

from __future__ import annotations

import os

from cluster.archive.format import ArchiveError, RecoveryReport
from cluster.archive.reader import ScanStatus, check_file, scan
from cluster.archive.writer import Output


def recover(src, dst, *, overwrite: bool = False) -> RecoveryReport:
    """Copy every complete episode of ``src`` (e.g. a killed writer's ``.partial``) into a clean ``dst``.

    The scan reads records in file order, skips corrupt chunks (listed in the report's ``warnings``)
    and ends at a torn tail; every episode whose commit record and steps were read is copied message
    for message (same channels, metadata, times), the rest are dropped and counted. ``dst`` is
    written as ``dst.recovering`` and renamed when done; on an error it is removed.

    Raises:
        ArchiveError: ``src`` missing or not an archive, or holding no complete episode (then nothing is written);
            ``dst`` is ``src`` or exists (without overwrite).
    """
    src, dst = os.fspath(src), os.fspath(dst)
    check_file(src)
    if os.path.abspath(src) == os.path.abspath(dst):
        raise ArchiveError("recover writes a new file: --out must differ from the damaged file")
    status = ScanStatus()
    groups = scan(src, status)
    first = next(groups, None)  # raises ArchiveError for a non-archive before dst is created
    if status.header is None:  # empty, or cut inside its header: no episode, and nothing that says it is ocv2's
        raise ArchiveError(f"{src!r}: nothing to recover ({status.tail_error or 'no header record'})")
    if first is None:  # a copy would be a finished archive of no episode: it looks like a result and holds none
        why = [f"{status.orphan_messages} message(s) of episodes never committed"] if status.orphan_messages else []
        why += [status.tail_error] if status.tail_error else []
        raise ArchiveError(f"{src!r}: no complete episode to recover" + (f" ({'; '.join(why)})" if why else ""))
    # Not dst.partial: that is usually the source itself.
    out = Output(dst, chunk_size=1 << 20, compression="zstd", overwrite=overwrite, fsync=False, suffix=".recovering")
    episodes = transitions = 0
    ids: dict[int, int] = {}
    try:
        group = first
        while group is not None:
            ordered = sorted(  # steps and frames interleave by time, as written
                [*group.steps, *group.others], key=lambda m: (m.log_time, m.channel_id)
            )
            for message in [*ordered, group.commit]:
                channel_id = _copy_channel(out, status, message.channel_id, ids)
                out.mcap.add_message(channel_id, message.log_time, message.data, message.publish_time, message.sequence)
            out.commit()
            episodes += 1
            transitions += group.meta["steps"]
            group = next(groups, None)
        out.finish()
    except BaseException:
        out.abandon()
        if os.path.exists(out.partial):
            os.unlink(out.partial)  # a half-copied file is no recovery: leave nothing behind
        raise
    return RecoveryReport(
        dst,
        episodes,
        transitions,
        status.orphan_messages,
        status.finished,
        None if status.finished else status.tail_error,
        tuple(status.warnings),
    )


def _copy_channel(out: Output, status: ScanStatus, old_id: int, ids: dict[int, int]) -> int:
    if old_id not in ids:
        channel = status.channels[old_id]
        schema_id = 0
        if channel.schema_id:
            schema = status.schemas[channel.schema_id]
            schema_id = out.schema(schema.name, schema.encoding, schema.data)
        ids[old_id] = out.channel(channel.topic, channel.message_encoding, schema_id, dict(channel.metadata))
    return ids[old_id]
