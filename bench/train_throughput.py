#!/usr/bin/env python
"""Training throughput: env steps/s of one PPO update with the paper's configs, split rollout / update.

Configs (paper appendix D, one seed):

* ``rnn``: PPO-RNN self-play on grounded_coord_simple, view radius 2, negative rewards, random
  starts, recipe resampling; 256 envs x 256 steps, 4 epochs x 64 minibatches (65,536 steps/update).
* ``cnn``: PPO-CNN self-play on cramped_room, full view; 64 envs x 256 steps, 4 epochs x 16
  minibatches (16,384 steps/update).

For each, three jitted programs are timed after compilation and one warm-up call (median of
``--repeats``): the whole update (``ppo.advance`` of 1 update), the rollout alone (the same
``lax.scan`` of ``rollout_step``) and, by difference, the learning part (GAE + epochs).
``env steps/s = steps per update / seconds per update``. The paper's loop reaches about 400-670
(RNN) and 350-470 (CNN) env steps/s on this kind of 2-core machine
(``../shared/reference/training-reference.md``, Runtime); the target is >= 2x those.

Writes the block between ``<!-- train_throughput:start -->`` and ``<!-- train_throughput:end -->``
of docs/BENCHMARKS.md.

    python bench/train_throughput.py
    python bench/train_throughput.py --configs cnn --repeats 2 --out ''
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp

from sections import publish  # bench/ is sys.path[0] when a script runs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from population import ppo  # noqa: E402
from population.config import parse_config  # noqa: E402

START, END = "<!-- train_throughput:start -->", "<!-- train_throughput:end -->"
PAPER_RANGE = {"rnn": (400, 670), "cnn": (350, 470)}
CONFIGS = {
    "rnn": {
        "env": {"layout": "grounded_coord_simple", "agent_view_size": 2, "negative_rewards": True,
                "random_agent_positions": True, "sample_recipe_on_delivery": True},
        "model": {"kind": "rnn"},
        "ppo": {"lr": 2.5e-4, "num_envs": 256, "num_steps": 256, "num_minibatches": 64, "update_epochs": 4,
                "total_timesteps": 30_000_000, "rew_shaping_horizon": 15_000_000, "ent_coef": 0.01,
                "max_grad_norm": 0.25},
    },
    "cnn": {
        "env": {"layout": "cramped_room"},
        "model": {"kind": "cnn"},
        "ppo": {"lr": 4e-4, "num_envs": 64, "num_steps": 256, "num_minibatches": 16, "update_epochs": 4,
                "total_timesteps": 10_000_000, "rew_shaping_horizon": 5_000_000, "ent_coef": 0.04,
                "max_grad_norm": 0.5},
    },
}


def _timed(fn, arg, repeats: int) -> float:
    jax.block_until_ready(fn(arg))  # warm-up after compilation
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(name: str, repeats: int) -> dict:
    config = parse_config(CONFIGS[name])
    trainer = ppo.make_trainer(config)
    state = ppo.init_population(trainer, [0])
    state = ppo.take_seed(state, 0)

    def rollout(s):
        carry = ppo.StepCarry(s, jnp.float32(1.0))
        carry, transitions = jax.lax.scan(lambda c, x: ppo.rollout_step(trainer, None, None, c, x), carry, None,
                                          length=config.ppo.num_steps)
        return carry.state.key, transitions.reward

    update = jax.jit(lambda s: ppo.advance(trainer, s, 1)[1])
    rollout_only = jax.jit(rollout)
    started = time.perf_counter()
    jax.block_until_ready(update(state))
    compile_s = time.perf_counter() - started
    t_update = _timed(update, state, repeats)
    t_rollout = _timed(rollout_only, state, repeats)
    steps = config.ppo.steps_per_update
    return {"name": name, "layout": config.env_kwargs["layout"], "steps": steps, "update_s": t_update,
            "rollout_s": t_rollout, "learn_s": max(t_update - t_rollout, 0.0), "sps": steps / t_update,
            "compile_s": compile_s, "config": config}


def table(results, repeats: int) -> str:
    lines = [
        START,
        "## Training throughput (`bench/train_throughput.py`)",
        "",
        f"Measured {_dt.date.today()} on {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"jax {jax.__version__} ({jax.default_backend()}); one seed, median of {repeats} updates after a warm-up.",
        "",
        "| config | layout | steps/update | s/update | rollout | learning (GAE+epochs) | env steps/s | paper loop | speed-up |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lo, hi = PAPER_RANGE[r["name"]]
        lines.append(
            f"| {r['name'].upper()} | {r['layout']} | {r['steps']:,} | {r['update_s']:.1f} | "
            f"{r['rollout_s']:.1f} s ({100 * r['rollout_s'] / r['update_s']:.0f} %) | "
            f"{r['learn_s']:.1f} s ({100 * r['learn_s'] / r['update_s']:.0f} %) | {r['sps']:,.0f} | {lo}-{hi} | "
            f"{r['sps'] / hi:.1f}-{r['sps'] / lo:.1f}x |")
    lines += [
        "",
        "RNN = PPO-RNN self-play, grounded_coord_simple, view 2 (paper RNN-SP column: 256 envs x 256 steps, "
        "4 epochs x 64 minibatches). CNN = PPO-CNN, cramped_room, full view (paper classic column: 64 x 256, "
        "4 x 16). The paper-loop range is the reference's component estimate for its code on this kind of "
        "2-core CPU; JaxMARL's own script measured 26 env steps/s there.",
        "",
        "What made the difference: XLA:CPU's convolution and especially its gradient are slow on these tiny "
        "grids. `population.networks.SameConv` computes the same SAME-padded convolution as shifted slices + "
        "one matmul (identical parameters, equal to `nn.Conv` to 2e-6): with `flax.linen.Conv` the CNN update "
        "above took 104 s (158 env steps/s), the rollout alone 3.5 s instead of 0.3 s.",
        END,
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=["rnn", "cnn"], choices=sorted(CONFIGS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="docs/BENCHMARKS.md")
    args = parser.parse_args(argv)
    results = []
    for name in args.configs:
        print(f"measuring {name} ...", flush=True)
        r = measure(name, args.repeats)
        print(f"  {r['sps']:,.0f} env steps/s (update {r['update_s']:.1f} s, rollout {r['rollout_s']:.1f} s, "
              f"compile {r['compile_s']:.0f} s)", flush=True)
        results.append(r)
    block = table(results, args.repeats)
    publish(block, args.out, START, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
