"""Which way round Coordination Ring each seed's agents walk (SP, SA or any run of the layout).

    python docs/results/table1_coord_ring/ring_direction.py archive STUDY_DIR/runs/sp/archive/xp [--episodes 100]
    python docs/results/table1_coord_ring/ring_direction.py snapshots STUDY_DIR/runs/sp [--updates 0,30,61,122,305]

``archive``: every ordered pair (seat-0 seed, seat-1 seed) of the final checkpoints, read from the study's
cross-play archive (the first N episodes of each pair). ``snapshots``: each seed in self-play at kept
checkpoints, N fresh episodes each (sampled actions, a fixed key).

The share of each seat's moves between ring cells that go clockwise as the layout is drawn (y grows
downward, so a rise of atan2(y - 2, x - 2) about the centre counter is clockwise on screen), and the mean
return over the same episodes. Two agents that walk opposite ways block each other in the one-cell-wide
ring; a population that all walks the same way has no such conflict.
"""

import argparse
import functools
import sys
from pathlib import Path

import jax
import numpy as np

from cluster.archive.reader import ArchiveReader
from population.behaviour import clockwise_moves
from population.evaluation import play_episodes
from population.policy import load, policy_env

CENTRE = (2, 2)  # (x, y) of the ring's centre counter in coord_ring


def from_archive(folder: str, per_pair: int) -> None:
    files = sorted(Path(folder).glob("seat0_seed_*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not files:
        sys.exit(f"{folder}: no seat0_seed_<i>.mcap cross-play archive here")
    print("| seat 0 | seat 1 | clockwise share, seat 0 | clockwise share, seat 1 | mean return | episodes |")
    print("|---:|---:|---:|---:|---:|---:|")
    for path in files:
        reader = ArchiveReader(path)
        metas = reader.episodes()
        for row, col in sorted({tuple(m["seeds"]) for m in metas}):
            chosen = [k for k, m in enumerate(metas) if tuple(m["seeds"]) == (row, col)][:per_pair]
            clockwise, moves, returns = np.zeros(2), np.zeros(2), []
            for k in chosen:
                episode = reader.episode(k)
                c, m = clockwise_moves(episode.states.agents.x, episode.states.agents.y, CENTRE)
                clockwise += c
                moves += m
                returns.append(episode.meta["return"])
            share = clockwise / np.maximum(moves, 1)
            print(
                f"| {row} | {col} | {share[0]:.2f} | {share[1]:.2f} | {np.mean(returns):.1f} | {len(chosen)} |",
                flush=True,
            )


@functools.lru_cache
def self_play(apply, hidden_size: int, env, episodes: int):
    """One compiled self-play rollout (every state kept) shared by all seeds and snapshots of a run."""
    return jax.jit(
        lambda params, key: play_episodes(apply, hidden_size, env, (params, params), key, episodes, keep_every=1)
    )


def from_snapshots(run_dir: str, updates: list[int], episodes: int, seeds: int) -> None:
    print(
        "| update | " + " | ".join(f"seed {s}: clockwise share (seat 0, seat 1), return" for s in range(seeds)) + " |"
    )
    print("|---:|" + "---|" * seeds)
    for update in updates:
        cells = []
        for seed in range(seeds):
            policy = load(run_dir, seed=seed, checkpoint=update)
            play = self_play(policy.apply, policy.hidden_size, policy_env(policy.env), episodes)
            played = play(policy.params, jax.random.PRNGKey(7))
            agents = played.states.agents  # [R, S, seat]
            clockwise, moves = clockwise_moves(agents.x, agents.y, CENTRE, time_axis=1)
            share = clockwise / np.maximum(moves, 1)
            cells.append(f"{share[0]:.2f}, {share[1]:.2f}, {float(np.mean(played.returns)):.0f}")
        print(f"| {update} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="source", required=True)
    archive = sub.add_parser("archive")
    archive.add_argument("folder")
    archive.add_argument("--episodes", type=int, default=100)
    snapshots = sub.add_parser("snapshots")
    snapshots.add_argument("run_dir")
    snapshots.add_argument("--updates", default="0,30,61,122,305")
    snapshots.add_argument("--episodes", type=int, default=32)
    snapshots.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    if args.source == "archive":
        from_archive(args.folder, args.episodes)
    else:
        from_snapshots(args.run_dir, [int(u) for u in args.updates.split(",")], args.episodes, args.seeds)


if __name__ == "__main__":
    main()
