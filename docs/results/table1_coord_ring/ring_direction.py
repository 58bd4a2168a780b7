"""Which way round Coordination Ring each SP seed's agents walk, read from the study's cross-play archive.

    python docs/results/table1_coord_ring/ring_direction.py STUDY_DIR/runs/sp/archive/xp [EPISODES_PER_PAIR]

For every ordered pair (seat-0 seed, seat-1 seed) of the final checkpoints: the share of each seat's moves
between ring cells that go clockwise as the layout is drawn (y grows downward, so a rise of
atan2(y - 2, x - 2) about the centre counter is clockwise on screen), and the pair's mean return over the
same episodes. Two populations that walk opposite ways block each other in the one-cell-wide ring; one
that all walks the same way has no such conflict.
"""

import sys
from pathlib import Path

import numpy as np

from cluster.archive.reader import ArchiveReader

CENTRE = 2  # the ring's centre counter is at (2, 2) in coord_ring


def clockwise_moves(episode) -> tuple[np.ndarray, np.ndarray]:
    """Per seat: how many of its moves went clockwise, and how many moves it made."""
    agents = episode.states.agents
    angle = np.arctan2(agents.y.astype(float) - CENTRE, agents.x.astype(float) - CENTRE)
    turn = (np.diff(angle, axis=0) + np.pi) % (2 * np.pi) - np.pi
    moved = np.abs(turn) > 1e-9
    return (moved & (turn > 0)).sum(0), moved.sum(0)


def main(folder: str, per_pair: int) -> None:
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
                c, m = clockwise_moves(episode)
                clockwise += c
                moves += m
                returns.append(episode.meta["return"])
            share = clockwise / np.maximum(moves, 1)
            print(
                f"| {row} | {col} | {share[0]:.2f} | {share[1]:.2f} | {np.mean(returns):.1f} | {len(chosen)} |",
                flush=True,
            )


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 100)
