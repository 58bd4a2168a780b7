#!/usr/bin/env python
"""Population scaling: one process (seeds vmapped) vs Ray (one actor per seed), SA collection share,
MCAP archive overhead and archive size.

Part A trains the same N-seed state-augmented population twice from scratch, with the paper's
classic Cramped Room CNN settings (64 envs x 256 steps per update, SA with 10 rollouts per pair and
every 10th state kept) shortened to ``--updates`` updates in 2 SA iterations (every collection
episode archived, as by default):

  (a) ``--backend local``: one process, seeds vmapped in one jitted program;
  (b) ``--backend ray``: a local Ray, one actor per seed (``cluster.num_cpus`` = cores / N).

Both use the same cores, so "per unit of compute" is the plain ratio of their population env steps/s.
Steady state is timed between the coordinator's chunk ends after the first chunk (compilation and,
for Ray, start-up are reported separately). SA collection time is measured inside those runs.

Part B plays one SA collection at the paper's full settings (K = 10 seeds -> 100 ordered pairs x
10 episodes x 400 steps = 400,000 transitions) with and without recording every transition to MCAP,
and writes the archive: MCAP overhead and archive size per 1M transitions are measured there. The
shares at paper settings combine B with the training rate of A: one SA iteration trains 10 seeds x
1M env steps (10M steps, 10 iterations).

Writes the block between ``<!-- population_scaling:start -->`` and ``<!-- population_scaling:end -->``
of docs/BENCHMARKS.md.

    python bench/population_scaling.py
    python bench/population_scaling.py --seeds 2 --updates 6 --out ''
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import shutil
import sys
import tempfile
import time

from sections import publish  # bench/ is sys.path[0] when a script runs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("RAY_AUTH_MODE", "disabled")

import jax  # noqa: E402

from cluster.runtime import coordinator  # noqa: E402
from population.config import load_config  # noqa: E402

START, END = "<!-- population_scaling:start -->", "<!-- population_scaling:end -->"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER_CONFIG = os.path.join(ROOT, "configs", "paper", "classic_cramped_room_sa.yaml")
PAPER_SEEDS, PAPER_STEPS_PER_SEED, PAPER_ITERATIONS = 10, 10_000_000, 10


class Timeline:
    """Chunk-end times (``on_chunk``) and SA collection intervals of one run."""

    def __init__(self):
        self.chunks, self.collections = [], []
        self._collect = coordinator.sa_buffer

    def sa_buffer(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self._collect(*args, **kwargs)
        finally:
            self.collections.append((start, time.perf_counter()))

    def on_chunk(self, update, _workers, _rows=()):  # the coordinator also passes the merged rows
        self.chunks.append((update, time.perf_counter()))


def population_config(seeds: int, updates: int, backend: str):
    steps = 64 * 256 * updates
    overrides = [
        f"population.num_seeds={seeds}",
        f"ppo.total_timesteps={steps}",
        f"ppo.rew_shaping_horizon={steps}",
        "population.sa.iterations=2",
        f"run.checkpoint_every={max(1, updates // 3)}",
        "eval.gifs=0",
    ]
    if backend == "ray":
        overrides += [f"cluster.num_cpus={max(os.cpu_count() or 1, 1) / seeds:.3f}"]
    return load_config(PAPER_CONFIG, overrides)


def run_population(backend: str, seeds: int, updates: int) -> dict:
    config = population_config(seeds, updates, backend)
    timeline = Timeline()
    coordinator.sa_buffer = timeline.sa_buffer  # the loop looks it up in the module at call time
    out = tempfile.mkdtemp(prefix=f"ocv2-scaling-{backend}-")
    started = time.perf_counter()
    ray_start = 0.0
    try:
        if backend == "local":
            from cluster.runtime.local import LocalWorkers

            coordinator.train(
                config, out, LocalWorkers, show_progress=False, evaluate=False, on_chunk=timeline.on_chunk
            )
        else:
            import ray

            from cluster.runtime.ray_backend import train_population

            t = time.perf_counter()
            ray.init(include_dashboard=False, configure_logging=False)
            ray_start = time.perf_counter() - t
            try:
                train_population(config, out, show_progress=False, evaluate=False, on_chunk=timeline.on_chunk)
            finally:
                ray.shutdown()
        wall = time.perf_counter() - started
        archive_bytes = sum(
            os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.join(out, "archive")) for f in fs
        )
    finally:
        coordinator.sa_buffer = timeline._collect
        shutil.rmtree(out, ignore_errors=True)
    (u0, t0), (u1, t1) = timeline.chunks[0], timeline.chunks[-1]
    window = t1 - t0
    sa_in_window = sum(max(0.0, min(e, t1) - max(s, t0)) for s, e in timeline.collections)
    steps = seeds * (u1 - u0) * config.ppo.steps_per_update
    return {
        "backend": backend,
        "wall_s": wall,
        "ray_start_s": ray_start,
        "first_chunk_s": t0 - started,
        "steady_steps_per_s": steps / window,
        "training_steps_per_s": steps / (window - sa_in_window),
        "sa_share": sa_in_window / window,
        "sa_s": sum(e - s for s, e in timeline.collections),
        "collections": len(timeline.collections),
        "archive_bytes": archive_bytes,
        "window_updates": u1 - u0,
    }


def sa_at_paper_settings() -> dict:
    """One SA collection of 10 seeds (100 ordered pairs) with and without recording + MCAP writing."""
    from cluster.archive import ArchiveWriter, env_meta, record_episodes
    from cluster.runtime.runstate import hidden_size
    from population import ppo
    from population.sa import all_pairs, collect_pairs

    config = load_config(PAPER_CONFIG)
    trainer = ppo.make_trainer(config)
    params = ppo.init_population(trainer, range(PAPER_SEEDS)).params
    env = ppo.eval_env(config)
    key = jax.random.PRNGKey(0)
    sa = config.population.sa
    collect = lambda record, pairs: collect_pairs(
        trainer.network.apply, hidden_size(trainer), env, params, key, sa, pairs, record=record
    )
    for record in (False, True):  # compile both programs (one K-pair chunk) before timing
        jax.block_until_ready(jax.tree.leaves(collect(record, all_pairs(PAPER_SEEDS)[:PAPER_SEEDS])[0].states))
    start = time.perf_counter()
    part, _ = collect(False, None)
    jax.block_until_ready(jax.tree.leaves(part.states))
    plain = time.perf_counter() - start
    start = time.perf_counter()
    part, recorded = collect(True, None)
    recorded = jax.device_get(recorded)
    played = time.perf_counter() - start
    path = os.path.join(tempfile.mkdtemp(prefix="ocv2-scaling-mcap-"), "sa.mcap")
    start = time.perf_counter()
    with ArchiveWriter(path) as writer:
        base = env_meta(env)
        for index, (i, j) in enumerate(part.pairs):
            record_episodes(writer, env, jax.tree.map(lambda x: x[index], recorded), {**base, "seeds": [i, j]})
    written = time.perf_counter() - start
    size = os.path.getsize(path)
    shutil.rmtree(os.path.dirname(path), ignore_errors=True)
    transitions = len(part.pairs) * sa.rollouts_per_pair * env.max_steps
    return {"plain_s": plain, "recorded_s": played, "write_s": written, "bytes": size, "transitions": transitions}


def render(results: list[dict], paper: dict, seeds: int, updates: int) -> str:
    local, ray = results
    training_rate = local["training_steps_per_s"]
    train_iteration = PAPER_SEEDS * PAPER_STEPS_PER_SEED / PAPER_ITERATIONS / training_rate
    sa_share_paper = paper["plain_s"] / (paper["plain_s"] + train_iteration)
    mcap_extra = paper["recorded_s"] + paper["write_s"] - paper["plain_s"]
    mcap_share = mcap_extra / (paper["plain_s"] + mcap_extra + train_iteration)
    per_million = paper["bytes"] / paper["transitions"] * 1e6
    ratio = ray["steady_steps_per_s"] / local["steady_steps_per_s"]
    ok = lambda good: "yes" if good else "**no**"
    lines = [
        START,
        "## Population scaling (`bench/population_scaling.py`)",
        "",
        f"Measured {_dt.date.today()} on {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"no GPU, jax {jax.__version__}. Part A: {seeds}-seed SA population, paper classic Cramped Room CNN "
        f"settings, {updates} updates of 16,384 env steps per seed, 2 SA iterations (every collection episode "
        "archived), trained from scratch by each backend; steady state = after the first chunk.",
        "",
        "| backend | wall (incl. start-up) | Ray start | first chunk (compile) | population env steps/s (steady, incl. SA) "
        "| training-only env steps/s | SA collection share | archive |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['backend']} | {r['wall_s']:.0f} s | {r['ray_start_s']:.1f} s | {r['first_chunk_s']:.0f} s | "
            f"{r['steady_steps_per_s']:,.0f} | {r['training_steps_per_s']:,.0f} | {100 * r['sa_share']:.1f} % "
            f"| {r['archive_bytes'] / 1e6:.1f} MB |"
        )
    lines += [
        "",
        f"Part B: one SA collection at the paper's settings (10 seeds, 100 ordered pairs x 10 episodes x 400 steps = "
        f"{paper['transitions']:,} transitions, untrained CNNs): {paper['plain_s']:.1f} s keeping every 10th state; "
        f"{paper['recorded_s']:.1f} s keeping every transition + {paper['write_s']:.1f} s writing MCAP "
        f"({paper['bytes'] / 1e6:.1f} MB).",
        "",
        "| target | measured | met |",
        "|---|---|---|",
        f"| Ray within 5 % of one process per unit of compute | Ray {ray['steady_steps_per_s']:,.0f} vs "
        f"{local['steady_steps_per_s']:,.0f} env steps/s = {100 * ratio:.1f} % | {ok(ratio >= 0.95)} |",
        f"| SA collection <= 10 % of wall time at paper settings | {100 * sa_share_paper:.1f} % (collection "
        f"{paper['plain_s']:.0f} s per iteration vs {train_iteration:,.0f} s training 10 x 1M steps at "
        f"{training_rate:,.0f} steps/s) | {ok(sa_share_paper <= 0.10)} |",
        f"| MCAP logging <= 5 % at paper settings | {100 * mcap_share:.2f} % ({mcap_extra:.1f} s extra per "
        f"iteration) | {ok(mcap_share <= 0.05)} |",
        f"| archive size per 1M transitions | {per_million / 1e6:.1f} MB (zstd, full states + actions + rewards) | - |",
        END,
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--updates", type=int, default=12)
    parser.add_argument(
        "--out",
        default=os.path.join(ROOT, "docs", "BENCHMARKS.md"),
        help="Markdown file whose block is replaced ('' to only print)",
    )
    args = parser.parse_args(argv)
    results = []
    for backend in ("local", "ray"):
        print(f"part A: {backend} ...", flush=True)
        results.append(run_population(backend, args.seeds, args.updates))
        print(results[-1], flush=True)
    print("part B: SA collection at paper settings ...", flush=True)
    paper = sa_at_paper_settings()
    print(paper, flush=True)
    block = render(results, paper, args.seeds, args.updates)
    publish(block, args.out, START, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
