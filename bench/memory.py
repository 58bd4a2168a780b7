#!/usr/bin/env python
"""Peak memory of a training process against seeds per process, for population/memory.py's estimate.

Trains each paper config with ``--backend local`` (one process, seeds vmapped: what one Ray actor with
``seeds_per_actor`` seeds runs) at the paper's ``num_envs``/``num_steps`` but a single PPO update, with
a one-episode cross-play and no GIFs or archives, and reads the process's peak resident memory from
the kernel (``os.wait4``'s rusage of that child alone). A straight line through the points gives the
fixed cost of a process and the cost of each further seed; ``population.memory`` uses those
numbers (docs/cluster.md, "Memory").

    python bench/memory.py                        # both kinds, 2 / 4 / 8 seeds
    python bench/memory.py --seeds 1 2 --kinds cnn
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIGS = {"cnn": "configs/paper/classic_cramped_room_sp.yaml", "rnn": "configs/paper/v2_grounded_coord_simple_sp.yaml"}
STEPS_PER_UPDATE = {"cnn": 64 * 256, "rnn": 256 * 256}


def peak_mib(kind: str, seeds: int) -> float:
    """Peak RSS (MiB) of one ``ocv2 train --backend local`` process training ``seeds`` seeds for one update."""
    steps = STEPS_PER_UPDATE[kind]
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            "-m",
            "cluster.cli",
            "train",
            CONFIGS[kind],
            "--backend",
            "local",
            "--quiet",
            "--out",
            os.path.join(tmp, "run"),
            "--set",
            f"population.num_seeds={seeds}",
            "--set",
            f"ppo.total_timesteps={steps}",
            "--set",
            "eval.episodes=1",
            "--set",
            "eval.gifs=0",
            "--set",
            "archive.xp=false",
        ]
        env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
        process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
        _, status, usage = os.wait4(process.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"{kind} with {seeds} seeds failed: {' '.join(command)}")
    return usage.ru_maxrss / 1024  # Linux reports KiB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", nargs="+", default=["cnn", "rnn"], choices=sorted(CONFIGS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[2, 4, 8])
    args = parser.parse_args()
    for kind in args.kinds:
        points = []
        for seeds in args.seeds:
            points.append((seeds, peak_mib(kind, seeds)))
            print(f"{kind} {CONFIGS[kind]}: {seeds} seed(s) -> peak RSS {points[-1][1]:.0f} MiB", flush=True)
        if len(points) > 1:
            n = len(points)
            mean_x = sum(x for x, _ in points) / n
            mean_y = sum(y for _, y in points) / n
            slope = sum((x - mean_x) * (y - mean_y) for x, y in points) / sum((x - mean_x) ** 2 for x, _ in points)
            print(f"{kind}: {mean_y - slope * mean_x:.0f} MiB + {slope:.0f} MiB per seed", flush=True)


if __name__ == "__main__":
    main()
