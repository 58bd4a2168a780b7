#!/usr/bin/env python
"""Cross-play of exported files: one job per file, or the files of one network joined in one job?

``ocv2 xp --rows f0 ... f9`` of ten exported one-policy files (a published population played again) makes ten
one-policy sources. Each row used to be ten jobs, one per file, each a vmapped program over one partner; now
neighbouring sources of one network join in one job (``cluster.runtime.crossplay.column_batches``), a program over
all ten partners. This script plays the same ``--rows`` rows of such a matrix both ways, in this process as
``--backend local`` does, on freshly initialised networks of ``--config`` (the weights do not change the work),
checks that the returns are equal, and times each row. The first row of each way includes compilation and is
reported apart. Writes the block between ``<!-- xp_files:start -->`` and ``<!-- xp_files:end -->`` of
docs/BENCHMARKS.md.

    python bench/xp_files.py                      # CNN Cramped Room, 4 rows of 10 x 10, 64 episodes per pair
    python bench/xp_files.py --out ''             # print only
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import platform
import sys
import time

import jax
import numpy as np
from sections import publish  # bench/ is sys.path[0] when a script runs
from xp_matrix import matrix_parser, parse_matrix_args, random_population

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from cluster.runtime import crossplay  # noqa: E402
from population.config import load_config  # noqa: E402
from population.policy import policy_env  # noqa: E402

START, END = "<!-- xp_files:start -->", "<!-- xp_files:end -->"


def one_policy_sources(group: crossplay.PolicyGroup) -> list[crossplay.PolicyGroup]:
    """``group``'s policies as one source each, as ``ocv2 xp`` resolves exported files."""
    return [
        dataclasses.replace(
            group,
            label=name,
            names=(name,),
            ids=(policy,),
            params=jax.tree.map(lambda x, k=k: x[k : k + 1], group.params),
        )
        for k, (name, policy) in enumerate(zip(group.names, group.ids))
    ]


def play_rows(files, rows: int, episodes: int, precision: str) -> dict[int, tuple[np.ndarray, list[float]]]:
    """Rows 0..rows-1 of the files' matrix both ways, interleaved row by row so that both see the same machine:
    {MAX_BATCH_POLICIES: (returns, seconds per row)} for 1 (one job per file) and the default (joined)."""
    ways = {1: ([], []), crossplay.MAX_BATCH_POLICIES: ([], [])}
    players, saved = crossplay.LocalPlayers(precision), crossplay.MAX_BATCH_POLICIES
    try:
        for row in files[:rows]:
            for batch, (returns, seconds) in ways.items():
                crossplay.MAX_BATCH_POLICIES = batch
                started = time.perf_counter()
                returns.append(crossplay.play_matrix([row], files, players, crossplay.xp_key(0), episodes).returns)
                seconds.append(time.perf_counter() - started)
    finally:
        crossplay.MAX_BATCH_POLICIES = saved
    return {batch: (np.concatenate(returns), seconds) for batch, (returns, seconds) in ways.items()}


def main(argv=None) -> int:
    parser = matrix_parser(
        __doc__, "configs/paper/classic_cramped_room_sp.yaml", 64, 4, "seat-0 rows played each way (the first compiles)"
    )
    parser.add_argument("--shared", default="", help="what else ran on the machine while measured, if anything")
    args = parse_matrix_args(parser, argv)

    config = load_config(args.config)
    env = policy_env(config.env_kwargs)
    files = one_policy_sources(random_population(config, args.policies))
    precision = config.run.precision
    ways = play_rows(files, args.rows, args.episodes, precision)
    (one_by_one, alone_s), (joined, joined_s) = ways[1], ways[crossplay.MAX_BATCH_POLICIES]
    np.testing.assert_array_equal(joined, one_by_one)  # the same returns, pair for pair
    alone_row, joined_row = float(np.median(alone_s[1:])), float(np.median(joined_s[1:]))
    steps = args.policies * args.episodes * env.max_steps  # env steps of one row
    lines = [
        START,
        "## Cross-play of exported files (`bench/xp_files.py`)",
        "",
        f"Measured {_dt.date.today().isoformat()} on {platform.machine()}, {os.cpu_count()} CPU cores"
        + (f" (shared with {args.shared} while measured)" if args.shared else " (nothing else running)")
        + f", jax {jax.__version__} ({jax.default_backend()}).",
        "",
        f"{args.policies} one-policy sources (what `ocv2 xp --rows f0 ... f{args.policies - 1}` of exported files "
        f"resolves; freshly initialised {config.model.kind.upper()} networks of {args.config}, layout "
        f"{config.env_kwargs['layout']}), {args.rows} seat-0 rows against all {args.policies}, {args.episodes} "
        f"episodes of {env.max_steps} steps per pair, in one process, the two ways row by row in turn. The returns of "
        "both ways are equal, pair for pair (checked by the script).",
        "",
        f"| jobs per row | first row (compiles) | one row after that (median of {args.rows - 1}; range) | env steps/s |",
        "|---|---:|---:|---:|",
        f"| one per file (before) | {alone_s[0]:.1f} s | {alone_row:.1f} s ({min(alone_s[1:]):.1f}-{max(alone_s[1:]):.1f}) "
        f"| {steps / alone_row:,.0f} |",
        f"| files of one network joined | {joined_s[0]:.1f} s | {joined_row:.1f} s ({min(joined_s[1:]):.1f}-"
        f"{max(joined_s[1:]):.1f}) | {steps / joined_row:,.0f} |",
        "",
        f"Joined, a row takes {joined_row / alone_row:.0%} of the time it took.",
        "",
        "Command: `python bench/xp_files.py`",
        END,
    ]
    publish("\n".join(lines), args.out, START, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
