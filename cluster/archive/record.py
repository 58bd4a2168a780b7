"""Archives and rollouts: recording pairs' episodes, and archived states as an SA reset buffer."""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cluster.archive.format import ArchiveError, env_meta
from cluster.archive.reader import ArchiveReader
from cluster.archive.writer import ArchiveWriter
from ocv2.config import build_config
from ocv2.layouts import Layout, get_layout
from ocv2.reset import validate_buffer
from ocv2.state import State
from population.record import jitted_play_recorded_pairs


def states_as_buffer(paths, keep_every: int = 10, layout: Layout | str | None = None) -> State:
    """Archived states as a state-augmentation reset buffer (a batched ``ocv2.State`` of jax arrays).

    Takes s_0, s_k, s_2k, ... (t < floor(T / k) k, as SA collection keeps them) of every complete episode of every
    file, in file and episode order. Use it as ``env.reset_state(key, state_buffer=buffer)``, an
    ``ocv2.make(..., initial_state_buffer=buffer)`` or the SA buffer of a training run.

    Args:
        paths: one archive path or a list of them.
        keep_every: k, the stride in time.
        layout: the layout the buffer is for; default the first episode's. Every episode must be of
            this kitchen.

    Raises:
        ArchiveError: an unfinished or damaged file, no complete episode, or an episode of another layout / shape.
    """
    if isinstance(keep_every, bool) or not isinstance(keep_every, (int, np.integer)) or keep_every < 1:
        raise ValueError(f"keep_every must be a positive integer, got {keep_every!r}")
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    target = None if layout is None else get_layout(layout)
    parts = []
    for path in paths:
        reader = ArchiveReader(path)
        if not reader.finished or reader.warnings:  # a killed writer's file, or skipped chunks: states lost quietly
            what = "is unfinished (its writer was killed or still runs)" if not reader.finished else "is damaged"
            detail = f" ({reader.warnings[0]})" if reader.warnings else ""
            raise ArchiveError(
                f"{os.fspath(path)!r} {what}{detail}; copy its complete episodes into a clean file with "
                "`ocv2 archive recover FILE --out FIXED.mcap` and name that file"
            )
        for index, meta in enumerate(reader.episodes()):
            if meta["steps"] < keep_every:  # SA collection keeps nothing of it: say so, not "no state" later
                raise ArchiveError(
                    f"{os.fspath(path)!r} episode {meta['episode']} has {meta['steps']} steps, fewer than "
                    f"keep_every={keep_every}: SA collection would keep none of its states"
                )
            episode_layout = reader.layout(index)
            if target is None:
                target = episode_layout
            if not _same_kitchen(episode_layout, target):
                raise ArchiveError(
                    f"{path!r} episode {meta['episode']} is on layout {episode_layout.name!r} "
                    f"({episode_layout.height}x{episode_layout.width}, {episode_layout.num_agents} agents), not "
                    f"{target.name!r} ({target.height}x{target.width}, {target.num_agents} agents): a reset buffer "
                    "holds states of one kitchen"
                )
        for episode in reader.iter_episodes():
            kept = episode.meta["steps"] // keep_every * keep_every  # as collect_pairs: t < T // k * k
            parts.append(jax.tree.map(lambda x: x[0:kept:keep_every], episode.states))
    if not parts:
        raise ArchiveError(f"no complete episode in {', '.join(map(repr, map(os.fspath, paths)))}")
    buffer = jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs)), *parts)
    try:
        validate_buffer(build_config(target), buffer)
    except (TypeError, ValueError) as error:
        raise ArchiveError(f"archived states do not fit layout {target.name!r}: {error}") from None
    return buffer


def _same_kitchen(a: Layout, b: Layout) -> bool:
    return (
        a.static_objects.shape == b.static_objects.shape
        and (a.static_objects == b.static_objects).all()
        and a.num_agents == b.num_agents
        and a.num_ingredients == b.num_ingredients
    )


def record_episodes(
    writer: ArchiveWriter, env, recorded, meta: dict | None = None, first_episode: int = 0
) -> list[int]:
    """Write the E episodes of one pair's ``population.record.Recorded`` (no leading pair axis).

    Each episode's metadata is ``env_meta(env)`` + ``meta`` + ``{"pair_episode": first_episode + e}``.
    Returns the archive indices.
    """
    host = jax.device_get(recorded)
    base = {**env_meta(env), **(meta or {})}
    indices = []
    for e in range(np.shape(host.actions)[0]):
        states = jax.tree.map(lambda x: x[e], host.states)
        meta_e = {**base, "pair_episode": first_episode + e}
        indices.append(
            writer.write_episode(
                meta_e,
                states,
                host.actions[e],
                host.rewards[e],
                host.shaped_rewards[e],
                host.dones[e],
                layout=env.layout,
            )
        )
    return indices


def record_pairs(
    writer: ArchiveWriter, apply, hidden_size: int, env, params_a, params_b, keys, episodes: int, metas: Sequence[dict]
) -> list[int]:
    """P pairs play ``episodes`` episodes each (``population.record``) and every episode is archived.

    ``params_a``/``params_b`` have a leading [P] axis (seat 0 / seat 1), ``keys`` is [P], ``metas``
    one dict per pair (e.g. ``{"method": "xp", "policies": [i, j], "seed": s}``). Pair p's episodes
    are exactly those ``play_episodes`` would play with ``keys[p]``. Returns the archive indices.
    """
    if len(metas) != np.shape(keys)[0]:
        raise ValueError(f"metas has {len(metas)} entries for {np.shape(keys)[0]} pairs")
    recorded = jitted_play_recorded_pairs(apply, hidden_size, env, episodes)(params_a, params_b, keys)
    recorded = jax.device_get(recorded)
    indices = []
    for p, meta in enumerate(metas):
        indices += record_episodes(writer, env, jax.tree.map(lambda x: x[p], recorded), meta)
    return indices
