#!/usr/bin/env python
"""Does our PPO learn? The paper's classic-layout setting on Cramped Room, as far as a time budget allows.

Trains ``--config`` (default: the paper's CNN self-play hyperparameters, appendix D tab:lim-hyp,
10M steps) for ``--seeds`` seeds with the *full* run's schedules (LR warm-up + cosine over 10M steps,
shaping annealed over 5M), stopping when ``--minutes`` are spent. Records the per-update sparse
(team) return and shaped return, draws the curve, and writes the block between
``<!-- learning:start -->`` and ``<!-- learning:end -->`` of docs/BENCHMARKS.md.

A uniformly random policy scores about 1 on Cramped Room (measured and printed with the same
evaluation code), so a sparse return far above that means soups are being delivered on purpose.
The paper reaches SP 259 at 10M steps.

    python bench/learning.py --minutes 60
    python bench/learning.py --minutes 2 --out ''      # smoke run, nothing written
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from sections import write_section  # bench/ is sys.path[0] when a script runs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from population import ppo  # noqa: E402
from population.config import load_config  # noqa: E402

START, END = "<!-- learning:start -->", "<!-- learning:end -->"


def random_policy_return(config, episodes: int = 64) -> float:
    """Mean team return of uniformly random actions (the 'nothing learned' line)."""
    from population.evaluation import play_episodes

    env = ppo.eval_env(config)
    uniform = lambda params, hidden, obs, reset: (hidden, jnp.zeros(obs.shape[:2] + (env.num_actions,)), None)
    result = jax.jit(lambda k: play_episodes(uniform, 0, env, (None, None), k, episodes))(jax.random.PRNGKey(123))
    return float(result.returns.mean())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/paper/classic_cramped_room_sp.yaml")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--chunk", type=int, default=5, help="updates per jitted call")
    parser.add_argument("--out", default="docs/BENCHMARKS.md")
    parser.add_argument("--plot", default="docs/img/learning_cramped_room.png")
    parser.add_argument("--csv", default="docs/img/learning_cramped_room.csv")
    args = parser.parse_args(argv)

    config = load_config(args.config, [f"population.num_seeds={args.seeds}"])
    trainer = ppo.make_trainer(config)
    seeds = list(range(args.seeds))
    states = ppo.init_population(trainer, seeds)
    advance = ppo.make_advance_population(trainer, args.chunk)
    budget = args.minutes * 60
    started = time.perf_counter()
    rows = []
    update = 0
    print(
        f"{config.env_kwargs['layout']}: {args.seeds} seed(s), paper schedule over {config.ppo.num_updates} "
        f"updates, budget {args.minutes:g} min",
        flush=True,
    )
    while update < config.ppo.num_updates and time.perf_counter() - started < budget:
        chunk_start = time.perf_counter()
        states, metrics = advance(states, None, None)
        metrics = jax.tree.map(np.asarray, metrics)
        wall = time.perf_counter() - chunk_start
        for u in range(args.chunk):
            rows.append(
                {
                    "update": int(metrics.update[0, u]),
                    "env_steps": int(metrics.env_steps[0, u]),
                    "sparse_return": float(np.nanmean(metrics.sparse_return[:, u]))
                    if not np.isnan(metrics.sparse_return[:, u]).all()
                    else float("nan"),
                    "shaped_return": float(np.nanmean(metrics.shaped_return[:, u]))
                    if not np.isnan(metrics.shaped_return[:, u]).all()
                    else float("nan"),
                    "wall_s": time.perf_counter() - started,
                }
            )
        update = rows[-1]["update"]
        print(
            f"  update {update:4d}  env steps {rows[-1]['env_steps']:>10,}  sparse {rows[-1]['sparse_return']:7.1f}"
            f"  shaped {rows[-1]['shaped_return']:7.1f}  {args.seeds * args.chunk * config.ppo.steps_per_update / wall:,.0f} steps/s",
            flush=True,
        )
        if args.csv:
            _write_csv(args.csv, rows)
    random_return = random_policy_return(config)
    table = _table(rows, config, args, random_return, time.perf_counter() - started)
    print(table)
    if args.plot:
        _plot(rows, args.plot, random_return, config)
    if args.out:
        write_section(args.out, table, START, END)
    return 0


def _write_csv(path, rows):
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _table(rows, config, args, random_return, wall) -> str:
    marks = sorted({max(1, round(f * len(rows))) - 1 for f in (0.1, 0.25, 0.5, 0.75, 1.0)})
    lines = [
        START,
        "## Learning: PPO-CNN self-play on Cramped Room (`bench/learning.py`)",
        "",
        f"Measured {_dt.date.today()} on {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"jax {jax.__version__} ({jax.default_backend()}); `python bench/learning.py --minutes {args.minutes:g} "
        f"--seeds {args.seeds}`. Config `{args.config}` (the paper's appendix-D CNN hyperparameters); the LR and "
        f"shaping schedules are those of the full {config.ppo.total_timesteps:,}-step run, so this is the start of "
        "the paper's curve, not a shortened run.",
        "",
        "| env steps | sparse return (team) | shaped return | wall time |",
        "|---:|---:|---:|---:|",
    ]
    for i in marks:
        r = rows[i]
        lines.append(
            f"| {r['env_steps']:,} | {r['sparse_return']:.1f} | {r['shaped_return']:.1f} | {r['wall_s'] / 60:.1f} min |"
        )
    lines += [
        "",
        f"Random policy (uniform actions, 64 episodes): {random_return:.1f}. Paper: SP 259 after 10M steps (GPU). "
        f"Sparse return = mean over environments of the last finished 400-step episode's team return; "
        f"{args.seeds} seed(s); total wall time {wall / 60:.1f} min. Curve: `docs/img/learning_cramped_room.png`, "
        "data: `docs/img/learning_cramped_room.csv`.",
        "",
        "![learning curve](img/learning_cramped_room.png)",
        END,
    ]
    return "\n".join(lines)


def _plot(rows, path, random_return, config):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["env_steps"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, [r["sparse_return"] for r in rows], label="sparse (team) return")
    ax.plot(steps, [r["shaped_return"] for r in rows], label="shaped return", alpha=0.7)
    ax.axhline(random_return, color="grey", ls="--", label="random policy")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(f"PPO-CNN self-play, {config.env_kwargs['layout']} (paper hyperparameters)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
