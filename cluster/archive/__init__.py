"""The trajectory archive: whole episodes (states, actions, rewards) in MCAP files.

The only package of the project that imports ``mcap``, and only when it is installed: without it (an
environment set up by hand) the package still imports and every archive operation is a one-line
``ArchiveError`` naming ``pip install mcap`` (``require_mcap``). Format, guarantees and commands are
documented in ``docs/archive.md``; in short:

* One file holds any number of episodes. Each episode is written as T + 1 ``step`` messages (state
  s_t plus the transition taken from it; the last message carries the final state s_T and a padding
  transition) followed by one ``episode`` message (JSON metadata). The ``episode`` message is the
  commit record: an episode counts only once it is on disk, and steps without one are dropped.
* ``step`` payloads are raw little-endian arrays concatenated in a fixed order; the field table
  (name, dtype, shape) and the layout are in the channel's metadata. Chunks are zstd-compressed.
* ``ArchiveWriter`` writes ``PATH.partial``, flushes a chunk at every episode end, and on close
  finishes the file and renames it to ``PATH``. A writer that is killed, hits a write error or is left by
  an exception leaves ``PATH.partial`` (when it holds an episode); ``recover`` (``ocv2 archive recover``)
  rewrites every complete episode of it into a clean file.
* Reading never needs the file's summary: ``ArchiveReader`` scans records in file order, skips a
  corrupt chunk with a warning, and so reads finished, unfinished and damaged files alike.

Modules, each importing only those before it: ``format`` (constants, schemas, field table),
``writer``, ``reader``, ``recover``, ``record`` (rollouts to archives, archives to SA buffers).
"""

from cluster.archive.format import (
    FORMAT_VERSION,
    MCAP_AVAILABLE,
    PARTIAL_SUFFIX,
    RESERVED_KEYS,
    ArchiveError,
    Episode,
    RecoveryReport,
    env_meta,
    require_mcap,
)
from cluster.archive.reader import ArchiveReader
from cluster.archive.record import record_episodes, record_pairs, states_as_buffer
from cluster.archive.recover import recover
from cluster.archive.writer import ArchiveWriter

__all__ = [
    "ArchiveError",
    "ArchiveReader",
    "ArchiveWriter",
    "Episode",
    "RecoveryReport",
    "env_meta",
    "record_episodes",
    "record_pairs",
    "recover",
    "require_mcap",
    "states_as_buffer",
    "FORMAT_VERSION",
    "MCAP_AVAILABLE",
    "PARTIAL_SUFFIX",
    "RESERVED_KEYS",
]
