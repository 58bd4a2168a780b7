#!/usr/bin/env python
"""How long does the paper's cross-play matrix take on this CPU? 10 RNN policies x 10 x 500 episodes.

The paper evaluates every ordered pair of 10 seeds (diagonal included) for 500 episodes of 400 steps
on its RNN layouts: 100 pairs x 500 x 400 = 20M environment steps and 40M network steps. This script
times exactly what ``ocv2 xp --rows RUN --backend local`` runs (``cluster.runtime.crossplay.play_matrix``,
one job per seat-0 policy, each a vmapped program over the 10 partners and 64-episode blocks) on 10
freshly initialised RNNs of ``--config`` (the weights do not change the work: every episode runs all
400 steps). The first row includes compilation and is reported apart; with ``--rows N < 10`` only N
rows are played and the full matrix is extrapolated from the steady rows (stated in the output).
Writes the block between ``<!-- xp_matrix:start -->`` and ``<!-- xp_matrix:end -->`` of docs/BENCHMARKS.md.

    python bench/xp_matrix.py                      # the full 10 x 10 x 500 matrix
    python bench/xp_matrix.py --rows 3             # 3 of 10 rows, extrapolated
    python bench/xp_matrix.py --rows 2 --episodes 64 --out ''   # quick look, nothing written
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import sys
import time

import jax
import numpy as np
from sections import publish  # bench/ is sys.path[0] when a script runs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from cluster.runtime import crossplay  # noqa: E402
from population.config import load_config  # noqa: E402
from population.evaluation import stack_params  # noqa: E402
from population.networks import init_params  # noqa: E402
from population.policy import network, policy_env  # noqa: E402
from population.xp import episode_blocks  # noqa: E402

START, END = "<!-- xp_matrix:start -->", "<!-- xp_matrix:end -->"
GOAL_MIN = 30.0


def random_population(config, num: int) -> crossplay.PolicyGroup:
    """``num`` freshly initialised networks of ``config`` as one group (what a run directory gives)."""
    env = policy_env(config.env_kwargs)
    net = network(config.model, config.ppo.activation, env.num_actions)
    params = [jax.tree.map(np.asarray, init_params(net, jax.random.PRNGKey(s), env.obs_shape)) for s in range(num)]
    names = tuple(f"seed_{s}" for s in range(num))
    return crossplay.PolicyGroup(
        "population",
        names,
        names,
        config.model,
        config.ppo.activation,
        config.env_kwargs,
        stack_params(params),
        "sp",
        0,
    )


class RowTimer(crossplay.LocalPlayers):
    """In-process player that records when each job (one seat-0 row) ends."""

    def __init__(self, precision: str):
        super().__init__(precision)
        self.ends, self.cpu = [], []

    def call(self, method, jobs):
        out = super().call(method, jobs)
        self.ends.append(time.perf_counter())
        self.cpu.append(time.process_time())
        return out


def matrix_parser(doc: str, config: str, episodes: int, rows: int, rows_help: str) -> argparse.ArgumentParser:
    """The options of the cross-play benchmarks (this one and bench/xp_files.py): which networks, how many
    policies, episodes per pair and seat-0 rows, and where the table goes; ``parse_matrix_args`` reads them."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=config)
    parser.add_argument("--policies", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=episodes)
    parser.add_argument("--rows", type=int, default=rows, help=rows_help)
    parser.add_argument("--out", default="docs/BENCHMARKS.md")
    return parser


def parse_matrix_args(parser: argparse.ArgumentParser, argv) -> argparse.Namespace:
    args = parser.parse_args(argv)
    if not 2 <= args.rows <= args.policies:
        parser.error("--rows must be between 2 (one compile row + one steady row) and --policies")
    return args


def main(argv=None) -> int:
    parser = matrix_parser(
        __doc__, "configs/paper/v2_grounded_coord_simple_sp.yaml", 500, 10, "seat-0 rows to play (fewer: extrapolate)"
    )
    args = parse_matrix_args(parser, argv)

    config = load_config(args.config)
    env = policy_env(config.env_kwargs)
    group = random_population(config, args.policies)
    rows = crossplay.PolicyGroup(
        group.label,
        group.names[: args.rows],
        group.ids[: args.rows],
        group.model,
        group.activation,
        group.env,
        jax.tree.map(lambda x: x[: args.rows], group.params),
        group.method,
        group.seed,
    )
    players = RowTimer(config.run.precision)  # as the runs of that config would be cross-played
    cpu_started = time.process_time()
    started = time.perf_counter()
    result = crossplay.play_matrix([rows], [group], players, crossplay.xp_key(0), args.episodes)
    total = time.perf_counter() - started
    summary_started = time.perf_counter()
    crossplay.summarize_matrix(result)
    summary_s = time.perf_counter() - summary_started

    ends = [started] + players.ends
    per_row = np.diff(ends)
    first, steady = per_row[0], per_row[1:]
    row_s = float(np.median(steady))
    row_cpu = float(np.median(np.diff([cpu_started] + players.cpu)[1:]))  # CPU seconds, all threads
    full_s = first + row_s * (args.policies - 1)
    steps = args.policies * args.episodes * env.max_steps  # env steps of one row
    measured = args.rows == args.policies
    blocks, size = episode_blocks(args.episodes)
    stamp = _dt.date.today().isoformat()
    how = "(measured)" if measured else f"(extrapolated: first row + {args.policies - 1} x steady row)"
    cores = os.cpu_count()
    lines = [
        START,
        "## Cross-play matrix time (`bench/xp_matrix.py`)",
        "",
        f"Measured {stamp} on {platform.machine()}, {cores} CPU cores (shared with other jobs while measured), "
        f"jax {jax.__version__} ({jax.default_backend()}).",
        "",
        f"The paper's matrix: {args.policies} RNN policies ({args.config}: {config.model.kind}, GRU "
        f"{config.model.gru_dim}, layout {config.env_kwargs['layout']}, view "
        f"{config.env_kwargs.get('agent_view_size')}) x {args.policies} partners x {args.episodes} episodes of "
        f"{env.max_steps} steps = {args.policies**2 * args.episodes * env.max_steps / 1e6:.0f}M env steps, played "
        f"by the code behind `ocv2 xp --rows RUN --backend local` in one process (one job per seat-0 policy: "
        f"{args.policies} pairs x {blocks} blocks of {size} episodes, vmapped).",
        "",
        "| what | time |",
        "|---|---:|",
        f"| first row (includes compilation) | {first:.1f} s |",
        f"| one row after that (median of {len(steady)}) | {row_s:.1f} s ({steps / row_s:,.0f} env steps/s); "
        f"{row_cpu:.0f} CPU-seconds |",
        f"| rows played | {args.rows} of {args.policies} ({total:.0f} s) |",
        f"| full {args.policies}x{args.policies}x{args.episodes} matrix | **{full_s / 60:.1f} min** {how} |",
        f"| full matrix in CPU time (all cores together) | {(row_cpu * args.policies) / 60:.1f} CPU-minutes "
        f"(= {(row_cpu * args.policies) / 60 / cores:.1f} min if all {cores} cores were free and busy) |",
        f"| summary with seed-bootstrap CIs | {summary_s:.2f} s |",
        "",
        f"Goal: under {GOAL_MIN:.0f} min on this CPU -- {'met' if full_s / 60 < GOAL_MIN else 'not met'}. "
        "With `--backend ray` the rows spread over Ray workers (one per CPU by default), so on a machine "
        "with more cores the wall time drops about in proportion to the workers.",
        "",
        "Command: `python bench/xp_matrix.py"
        + (f" --rows {args.rows}" if not measured else "")
        + (f" --episodes {args.episodes}" if args.episodes != 500 else "")
        + "`",
        END,
    ]
    publish("\n".join(lines), args.out, START, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
