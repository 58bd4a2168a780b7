"""The archive's on-disk format: constants, JSON schemas, the step field table, layout specs, metadata.

Shared by the writer, the reader and recovery; imports no other part of the archive. The format is
described in ``docs/archive.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from ocv2.layouts import LAYOUTS, Layout, LayoutEdgeWarning
from ocv2.state import Agents, State

PROFILE = "ocv2-archive"  # MCAP header profile: marks an ocv2 archive
FORMAT_VERSION = 1
LIBRARY = f"ocv2-archive/{FORMAT_VERSION}"
PARTIAL_SUFFIX = ".partial"
EPISODE_TOPIC = "episode"
STEP_TOPIC = "step"
FRAMES_TOPIC = "frames"
STEP_ENCODING = "x-ocv2-fields"  # message encoding of ``step``: raw fields, table in channel metadata
MAGIC = b"\x89MCAP0\r\n"
#: Largest chunk (uncompressed) a reader decompresses: a larger claim is a corrupt or crafted chunk,
#: refused before anything is allocated. Writers keep ``chunk_size`` to a quarter of it, leaving
#: room for the message that overflows a chunk.
MAX_CHUNK_BYTES = 1 << 28

#: Keys the writer sets in every episode's metadata (a caller's ``meta`` must not use them, except
#: ``layout``, which must then name the episode's layout).
RESERVED_KEYS = (
    "format_version",
    "episode",
    "layout",
    "steps",
    "num_agents",
    "return",
    "shaped_return",
    "sequence_start",
    "log_time_start",
    "log_time_end",
)

COMPRESSION = ("zstd", "lz4", "none")  # chunk compressions (mcap's CompressionType, by lower-case name)

#: Whether the ``mcap`` package can be imported. It is a core dependency (``pip install ocv2`` brings it), but an
#: environment set up by hand (a GPU machine's ``pip install --no-deps``) may lack it. The archive's modules
#: import without it, so everything else runs (training with the archive turned off included); using the
#: archive then raises ``require_mcap``'s one-line ``ArchiveError``.
try:
    import mcap  # noqa: F401

    MCAP_AVAILABLE = True
except ImportError:
    MCAP_AVAILABLE = False

EPISODE_SCHEMA = {
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
RAW_IMAGE_SCHEMA = {
    "title": "foxglove.RawImage",
    "description": "A raw image",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {
                "sec": {"type": "integer", "minimum": 0},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
            },
        },
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


def require_mcap(turn_off: Sequence[str] = ()) -> None:
    """An ``ArchiveError`` naming ``pip install mcap`` when mcap is missing (and the ``--set`` settings of
    ``turn_off`` that would do without the archive)."""
    if MCAP_AVAILABLE:
        return
    alternative = f", or turn it off: {' '.join(f'--set {setting}' for setting in turn_off)}" if turn_off else ""
    raise ArchiveError(f"the trajectory archive needs the mcap package: pip install mcap{alternative}")


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
    warnings: tuple = ()  # corrupt chunks skipped and episodes lost with them


# ---------------------------------------------------------------------------------------------------
# State fields
# ---------------------------------------------------------------------------------------------------


def _state_treedef_and_names():
    dummy = State(
        agents=Agents(**{f.name: 0 for f in dataclasses.fields(Agents)}),
        **{f.name: 0 for f in dataclasses.fields(State) if f.name != "agents"},
    )
    leaves, treedef = jax.tree_util.tree_flatten_with_path(dummy)
    names = [jax.tree_util.keystr(path, simple=True, separator=".") for path, _ in leaves]
    return treedef, names


STATE_TREEDEF, STATE_NAMES = _state_treedef_and_names()
#: The transition fields after the state fields of every ``step`` message, with their dtypes.
TRANSITION_DTYPES = {"action": "<i4", "reward": "<f4", "shaped_reward": "<f4", "done": "|b1"}
TRANSITION_FIELDS = tuple(TRANSITION_DTYPES)


def field_table(state_leaves: Sequence[np.ndarray], num_agents: int) -> list[dict]:
    """(name, little-endian dtype, per-step shape) of every field of a step message, in order."""
    table = [
        {"name": "state." + name, "dtype": leaf.dtype.newbyteorder("<").str, "shape": list(leaf.shape[1:])}
        for name, leaf in zip(STATE_NAMES, state_leaves)
    ]
    shapes = {"action": [num_agents], "reward": [], "shaped_reward": [num_agents], "done": []}
    table += [{"name": name, "dtype": dtype, "shape": shapes[name]} for name, dtype in TRANSITION_DTYPES.items()]
    return table


def field_sizes(table: list[dict]) -> list[int]:
    return [np.dtype(f["dtype"]).itemsize * math.prod(f["shape"]) for f in table]


# ---------------------------------------------------------------------------------------------------
# Layouts and metadata
# ---------------------------------------------------------------------------------------------------


def layout_spec(layout: Layout) -> dict:
    return {
        "name": layout.name,
        "map": layout.to_string(),
        "agent_positions": [list(p) for p in layout.agent_positions],
        "num_ingredients": layout.num_ingredients,
        "possible_recipes": [list(r) for r in layout.possible_recipes],
    }


def layout_from_spec(spec: dict) -> Layout:
    """The built-in layout of that name if it is the same kitchen, else the stored one rebuilt."""
    builtin = LAYOUTS.get(spec["name"])
    if builtin is not None and layout_spec(builtin) == spec:
        return builtin
    with warnings.catch_warnings():  # the map was warned about when it was made; reading it back says nothing new
        warnings.simplefilter("ignore", LayoutEdgeWarning)
        static = Layout.from_string(spec["map"], spec["possible_recipes"], name=spec["name"]).static_objects
    return Layout(
        static_objects=static,
        agent_positions=tuple(tuple(p) for p in spec["agent_positions"]),
        num_ingredients=spec["num_ingredients"],
        possible_recipes=tuple(tuple(r) for r in spec["possible_recipes"]),
        name=spec["name"],
    )


def _json_default(value):
    if isinstance(value, (np.generic, np.ndarray, jax.Array)):
        return np.asarray(value).tolist()
    if isinstance(value, (tuple, set, frozenset)):
        return list(value)
    if isinstance(value, Layout):
        return value.name
    raise TypeError(f"episode metadata value {value!r} ({type(value).__name__}) is not JSON-serialisable")


def to_json(value) -> bytes:
    return json.dumps(value, default=_json_default, allow_nan=False, separators=(",", ":")).encode()


def env_meta(env) -> dict:
    """Episode metadata describing an ``ocv2.make`` environment: ``layout`` and ``env_params``."""
    config = env.config
    params = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name != "layout"}
    return {"layout": config.layout.name, "env_params": json.loads(to_json(params))}
