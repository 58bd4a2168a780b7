#!/usr/bin/env python
"""Environment throughput: ``ocv2`` vs. JaxMARL 0.2.0's OvercookedV2, side by side in one process.

Method (the same as ``bench_jaxmarl_ocv2.py``, the reference benchmark script):

* For every (implementation, layout, agent_view_size, batch) one jitted function runs
  ``jax.lax.scan`` over ``--steps`` (256) steps of ``jax.vmap``-ed ``env.step`` -- the auto-resetting
  JaxMARL dict API -- with uniformly random actions for every agent.  Observations (and the state)
  are carried through the scan and returned, so XLA cannot dead-code-eliminate them.
* Compile time and the first two runs are excluded (see ``Case``); every timed call ends in
  ``block_until_ready``.
* Each round times every case ``--repeats`` times; rounds (``--rounds``) are interleaved across all
  configurations *and* both implementations (their order alternates per round), so machine drift
  hits both alike.  The reported number is the median over all rounds x repeats.
* ``env steps/s = steps * batch / median_seconds`` (one env step = one transition of one kitchen,
  i.e. of all its agents together).

"Where the time goes" times, for ``ocv2`` only, the parts of ``env.step_arrays`` separately at one
configuration (default grounded_coord_simple, batch 1024, views None and 2), each in its own jitted
scan whose inputs change every iteration (carried state / fresh keys / a rotating pool of states),
so nothing can be hoisted out of the loop.

Writes ``docs/BENCHMARKS.md`` (only the block between ``<!-- env_throughput:start -->`` and
``<!-- env_throughput:end -->``; the rest of the file is kept) and optionally a JSON file.

Examples::

    python bench/env_throughput.py --quick            # smoke run (~1 min)
    python bench/env_throughput.py                    # the full default grid
    python bench/env_throughput.py --layouts cramped_room --views none --batches 1024 --rounds 3
"""

from __future__ import annotations

import argparse
import datetime as _dt
import gc
import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
from sections import write_section  # bench/ is sys.path[0] when a script runs

DEFAULT_LAYOUTS = ["cramped_room", "counter_circuit", "grounded_coord_simple", "demo_cook_wide"]
DEFAULT_VIEWS = ["none", "2"]
DEFAULT_BATCHES = [1, 64, 1024]
IMPLS = ["jaxmarl", "ocv2"]
START_MARK = "<!-- env_throughput:start -->"
END_MARK = "<!-- env_throughput:end -->"


# ---------------------------------------------------------------------------- factories
def make_jaxmarl(layout: str, view: int | None):
    from jaxmarl.environments.overcooked_v2 import OvercookedV2

    return OvercookedV2(layout=layout, agent_view_size=view)


def make_ocv2(layout: str, view: int | None):
    import ocv2

    return ocv2.make(layout, agent_view_size=view)


FACTORIES: dict[str, Callable] = {"jaxmarl": make_jaxmarl, "ocv2": make_ocv2}


def target_for(batch: int) -> float:
    return 3.0 if batch >= 64 else 1.5


def log(msg: str) -> None:
    print(msg, flush=True)


# ---------------------------------------------------------------------------- main sweep
def num_actions_of(env) -> int:
    n = getattr(env, "num_actions", None)
    if n is None:
        n = env.action_space(env.agents[0]).n
    return int(n)


def make_rollout(env, batch: int, steps: int):
    """(init, rollout): ``rollout`` scans ``steps`` auto-resetting vmapped ``env.step`` calls."""
    agents = list(env.agents)
    n_agents, n_actions = len(agents), num_actions_of(env)
    v_reset, v_step = jax.vmap(env.reset), jax.vmap(env.step)

    @jax.jit
    def init(key):
        return v_reset(jax.random.split(key, batch))

    @jax.jit
    def rollout(key, obs, state):
        def body(carry, _):
            obs, state, key, ret, n_done = carry
            key, k_act, k_step = jax.random.split(key, 3)
            acts = jax.random.randint(k_act, (n_agents, batch), 0, n_actions)
            act_dict = {a: acts[i] for i, a in enumerate(agents)}
            obs, state, rew, done, _info = v_step(jax.random.split(k_step, batch), state, act_dict)
            ret = ret + rew[agents[0]].sum()
            n_done = n_done + done["__all__"].sum()
            return (obs, state, key, ret, n_done), None

        carry0 = (obs, state, key, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32))
        (obs, state, _, ret, n_done), _ = jax.lax.scan(body, carry0, None, length=steps)
        return obs, state, ret, n_done

    return init, rollout, n_agents


class Case:
    """One compiled (impl, layout, view, batch) rollout and its timings."""

    def __init__(self, impl: str, layout: str, view, batch: int, steps: int, seed: int = 0):
        self.impl, self.layout, self.view, self.batch, self.steps = impl, layout, view, batch, steps
        env = FACTORIES[impl](layout, view)
        init, self.rollout, self.n_agents = make_rollout(env, batch, steps)
        self.key = jax.random.PRNGKey(seed)
        self.key, k0 = jax.random.split(self.key)
        self.obs, self.state = jax.block_until_ready(init(k0))
        # Two untimed warm-up runs: the first compiles; the second catches a recompile when the state
        # returned by `step` differs in type from the one `reset` made (e.g. weak_type), which would
        # otherwise land in the first timed run.
        t0 = time.perf_counter()
        self._run()
        self.compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        self._run()
        self.second_run_s = time.perf_counter() - t0
        self.times: list[float] = []
        self.sum_reward = 0.0
        self.episodes_done = 0

    def _run(self):
        self.key, k = jax.random.split(self.key)
        out = jax.block_until_ready(self.rollout(k, self.obs, self.state))
        self.obs, self.state = out[0], out[1]
        return out

    def repeats_for(self, repeats: int, min_time: float) -> int:
        """At least ``repeats`` runs, and enough to fill ``min_time`` seconds (estimated from the warm-up)."""
        return max(repeats, math.ceil(min_time / max(self.second_run_s, 1e-6)))

    def time(self, repeats: int) -> list[float]:
        new = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = self._run()
            new.append(time.perf_counter() - t0)
            self.sum_reward += float(out[2])
            self.episodes_done += int(out[3])
        self.times += new
        return new

    def result(self) -> dict:
        med = statistics.median(self.times)
        sps = self.steps * self.batch / med
        return {
            "impl": self.impl,
            "layout": self.layout,
            "agent_view_size": self.view,
            "batch": self.batch,
            "steps": self.steps,
            "num_agents": self.n_agents,
            "compile_plus_first_run_s": round(self.compile_s, 3),
            "second_warmup_run_s": round(self.second_run_s, 3),
            "times_s": [round(t, 5) for t in self.times],
            "median_s": round(med, 6),
            "env_steps_per_s": sps,
            "env_steps_per_s_min": self.steps * self.batch / max(self.times),
            "env_steps_per_s_max": self.steps * self.batch / min(self.times),
            "agent_steps_per_s": sps * self.n_agents,
            "sanity_sum_reward_agent0": self.sum_reward,
            "sanity_episodes_done": self.episodes_done,
        }


# ---------------------------------------------------------------------------- time split (ocv2)
SPLIT_PARTS = [
    ("transition", "(a) transition only: `ocv2.dynamics.transition` (+ key split, random actions)"),
    ("observations", "(b) observations only: `ocv2.observations.default_observations`"),
    ("reset_state", "(c) reset-state draw only: `env.reset_state`"),
    ("step_arrays", "(d) full `env.step_arrays` (+ key split, random actions)"),
    ("overhead", "(e) loop overhead only: key split + random actions (included in a and d)"),
    ("env_step_ocv2", "(f) ocv2 `env.step` (dict API, the main table's loop), re-timed here"),
    ("env_step_jaxmarl", "(g) jaxmarl `env.step` (dict API, the main table's loop), re-timed here"),
]
REFERENCE_PARTS = {"env_step_ocv2": "ocv2", "env_step_jaxmarl": "jaxmarl"}


def make_split_fns(env, batch: int, steps: int, pool_size: int = 64):
    """Jitted scans, one per part; each returns (fn, initial_carry).  fn(carry) -> carry."""
    import ocv2.dynamics
    import ocv2.observations

    cfg, n_agents, n_actions = env.config, env.num_agents, env.num_actions
    v_transition = jax.vmap(lambda k, s, a: ocv2.dynamics.transition(cfg, k, s, a))
    v_obs = jax.vmap(lambda s: ocv2.observations.default_observations(cfg, s))
    v_reset_state = jax.vmap(env.reset_state)
    v_step_arrays = jax.vmap(env.step_arrays)
    v_reset_arrays = jax.vmap(env.reset_arrays)

    def actions(k):
        return jax.random.randint(k, (batch, n_agents), 0, n_actions)

    key = jax.random.PRNGKey(1)
    key, k0 = jax.random.split(key)
    obs0, state0 = jax.jit(v_reset_arrays)(jax.random.split(k0, batch))

    # A pool of `pool_size` distinct batched states from a random auto-resetting rollout, for (b).
    @jax.jit
    def collect(key, state):
        def body(carry, _):
            key, state = carry
            key, k_a, k_s = jax.random.split(key, 3)
            out = v_step_arrays(jax.random.split(k_s, batch), state, actions(k_a))
            return (key, out.state), out.state

        # Walk 100 steps first so the pool is not all fresh kitchens.
        (key, state), _ = jax.lax.scan(lambda c, x: (body(c, x)[0], None), (key, state), None, length=100)
        _, pool = jax.lax.scan(body, (key, state), None, length=pool_size)
        return pool

    key, kp = jax.random.split(key)
    pool = jax.block_until_ready(collect(kp, state0))

    @jax.jit
    def run_transition(carry):
        def body(c, _):
            key, state, ret = c
            key, k_a, k_s = jax.random.split(key, 3)
            tr = v_transition(jax.random.split(k_s, batch), state, actions(k_a))
            return (key, tr.state, ret + tr.reward.sum()), None

        return jax.lax.scan(body, carry, None, length=steps)[0]

    @jax.jit
    def run_observations(carry):
        def body(c, i):
            obs, pool = c
            state = jax.tree.map(lambda p: jax.lax.dynamic_index_in_dim(p, i % pool_size, keepdims=False), pool)
            return (v_obs(state), pool), None

        return jax.lax.scan(body, carry, jnp.arange(steps, dtype=jnp.int32))[0]

    @jax.jit
    def run_reset_state(carry):
        def body(c, _):
            key, _state = c
            key, k = jax.random.split(key)
            return (key, v_reset_state(jax.random.split(k, batch))), None

        return jax.lax.scan(body, carry, None, length=steps)[0]

    @jax.jit
    def run_step_arrays(carry):
        def body(c, _):
            key, obs, state, ret = c
            key, k_a, k_s = jax.random.split(key, 3)
            out = v_step_arrays(jax.random.split(k_s, batch), state, actions(k_a))
            return (key, out.obs, out.state, ret + out.reward.sum()), None

        return jax.lax.scan(body, carry, None, length=steps)[0]

    @jax.jit
    def run_overhead(carry):
        def body(c, _):
            key, acc = c
            key, k_a, k_s = jax.random.split(key, 3)
            keys = jax.random.split(k_s, batch)
            acc = acc + actions(k_a).sum() + keys.sum().astype(jnp.int32)
            return (key, acc), None

        return jax.lax.scan(body, carry, None, length=steps)[0]

    zero = jnp.zeros((), jnp.float32)
    return {
        "transition": (run_transition, (key, state0, zero)),
        "observations": (run_observations, (v_obs(state0), pool)),
        "reset_state": (run_reset_state, (key, state0)),
        "step_arrays": (run_step_arrays, (key, obs0, state0, zero)),
        "overhead": (run_overhead, (key, jnp.zeros((), jnp.int32))),
    }


class SplitCase:
    def __init__(self, fn, carry):
        self.fn, self.carry = fn, carry
        t0 = time.perf_counter()
        self.carry = jax.block_until_ready(self.fn(self.carry))  # compile + first run
        self.compile_s = time.perf_counter() - t0
        self.carry = jax.block_until_ready(self.fn(self.carry))  # possible recompile (carry types settle)
        self.times: list[float] = []

    def time(self, repeats: int):
        for _ in range(repeats):
            t0 = time.perf_counter()
            self.carry = jax.block_until_ready(self.fn(self.carry))
            self.times.append(time.perf_counter() - t0)


# ---------------------------------------------------------------------------- environment info
def environment_info() -> dict:
    info = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "cpu_model": "unknown",
    }
    try:
        import jaxlib

        info["jaxlib"] = jaxlib.__version__
    except Exception:  # pragma: no cover
        info["jaxlib"] = "unknown"
    try:
        import jaxmarl

        info["jaxmarl"] = getattr(jaxmarl, "__version__", "unknown")
    except Exception:  # pragma: no cover
        info["jaxmarl"] = "not installed"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        info["load_avg_at_start"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    return info


# ---------------------------------------------------------------------------- reporting
def view_str(v) -> str:
    return "None" if v is None else str(v)


def results_table(rows_by_cfg, configs) -> tuple[str, dict]:
    head = "| layout | view | batch | jaxmarl env steps/s | ocv2 env steps/s | ratio (ocv2/jaxmarl) | target | met? |"
    sep = "|---|---|---:|---:|---:|---:|---:|:---:|"
    lines, ratios, met = [head, sep], [], 0
    for cfg in configs:
        jm, oc = rows_by_cfg[cfg]["jaxmarl"], rows_by_cfg[cfg]["ocv2"]
        ratio = oc["env_steps_per_s"] / jm["env_steps_per_s"]
        tgt = target_for(cfg[2])
        ok = ratio >= tgt
        ratios.append(ratio)
        met += ok
        lines.append(
            f"| {cfg[0]} | {view_str(cfg[1])} | {cfg[2]} | {jm['env_steps_per_s']:,.0f} "
            f"| {oc['env_steps_per_s']:,.0f} | {ratio:.2f}x | >={tgt:g}x | {'yes' if ok else 'NO'} |"
        )
    summary = {
        "cells": len(ratios),
        "met": int(met),
        "min_ratio": min(ratios) if ratios else float("nan"),
        "median_ratio": statistics.median(ratios) if ratios else float("nan"),
        "max_ratio": max(ratios) if ratios else float("nan"),
    }
    return "\n".join(lines), summary


def split_table(split_results, batch: int) -> str:
    views = list(split_results)
    head = (
        "| part | "
        + " | ".join(f"view {view_str(v)}: µs/step (batch {batch}) | view {view_str(v)}: % of (d)" for v in views)
        + " |"
    )
    sep = "|---|" + "---:|---:|" * len(views)
    lines = [head, sep]
    for part, label in SPLIT_PARTS:
        cells = []
        for v in views:
            us = split_results[v][part]["us_per_step"]
            full = split_results[v]["step_arrays"]["us_per_step"]
            cells.append(f"{us:,.1f} | {100 * us / full:.0f}%")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    cells = []
    for v in views:
        r = split_results[v]
        us = r["transition"]["us_per_step"] + r["observations"]["us_per_step"] + r["reset_state"]["us_per_step"]
        cells.append(f"{us:,.1f} | {100 * us / r['step_arrays']['us_per_step']:.0f}%")
    lines.append("| (a)+(b)+(c), for comparison with (d) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def build_markdown(
    info, args, command, table, summary, split_md, split_cfg, split_results, main_rows_by_cfg, wall_s
) -> str:
    out = [
        START_MARK,
        "## Environment throughput (bench/env_throughput.py)",
        "",
        "`ocv2` (this package) against the reference `jaxmarl==0.2.0` `OvercookedV2`, measured side by side"
        " in one process.",
        "",
        "### Machine / environment",
        "",
        f"- CPU: {info['cpu_model']} -- {info['cpu_count']} cores visible (`os.cpu_count()`)",
        f"- JAX backend devices: {', '.join(info['devices'])}; `XLA_FLAGS`={info['XLA_FLAGS'] or '(unset)'}",
        f"- jax {info['jax']}, jaxlib {info['jaxlib']}, jaxmarl {info['jaxmarl']}, Python {info['python']}"
        f" ({info['platform']})",
        f"- Date: {info['date']}; load average at start: {info.get('load_avg_at_start', 'n/a')};"
        f" wall time of the whole run: {wall_s / 60:.1f} min",
        "",
        "### Method",
        "",
        f"- Per (implementation, layout, view, batch): one jitted `jax.lax.scan` of {args.steps} steps of"
        " `jax.vmap`-ed `env.step` (the JaxMARL dict API, auto-resetting at episode end) with uniformly"
        " random actions for every agent; observations and state are carried through the scan and"
        " returned, so they cannot be dead-code-eliminated.",
        "- Compile time and the first two runs are excluded (the second catches a recompile when the state"
        " `step` returns differs in type from the one `reset` made); every timed call ends in"
        " `block_until_ready`.",
        f"- {args.rounds} round(s) per case, each of at least {args.repeats} timed runs and at least"
        f" {args.min_time:g} s of them (a batch-1 case makes hundreds of runs per round); rounds are"
        " interleaved across all configurations and both implementations (which one goes first"
        " alternates per round). Reported: median over all timed runs.",
        f"- env steps/s = {args.steps} x batch / median seconds (one env step = one transition of one"
        " kitchen, both agents). Ratio = ocv2 / jaxmarl. Target: >=3x for batch >= 64, >=1.5x for batch 1.",
        "- Both run on the CPU backend with XLA's default threading; the numbers are only comparable"
        " within one run (the machine is a shared VM).",
        "",
        "### Command",
        "",
        "```",
        command,
        "```",
        "",
        "### Results",
        "",
        table,
        "",
        f"**Summary:** {summary['met']}/{summary['cells']} cells meet the target; ratio ocv2/jaxmarl"
        f" min {summary['min_ratio']:.2f}x, median {summary['median_ratio']:.2f}x,"
        f" max {summary['max_ratio']:.2f}x.",
        "",
    ]
    if split_md:
        layout, batch = split_cfg
        out += [
            "### Where the time goes",
            "",
            f"`ocv2` only, {layout}, batch {batch}: each part timed alone in its own jitted"
            f" `lax.scan` of {args.steps} vmapped calls whose inputs change every iteration (the state"
            " is carried for (a), (c), (d); keys are split fresh every step; (b) reads a rotating pool"
            " of 64 distinct batched states from a random rollout), so nothing can be hoisted."
            f" Median of {args.rounds} x {args.repeats} runs; µs per scan step = per batch of {batch}"
            " environments.",
            "",
            split_md,
            "",
        ]
        out += [
            "(f) and (g) run the main table's loop again in this phase, so (d) can be compared with them"
            " under the same conditions; (d) and (f) run the same computation and differ only in the dict wrapper of `env.step` and the loop bookkeeping.",
            "",
        ]
        ref = []
        for v in split_results:
            row = main_rows_by_cfg.get((layout, v, batch))
            if row:
                ref.append(
                    f"view {view_str(v)}: full `env.step` (dict API) from the table above: jaxmarl"
                    f" {1e6 / row['jaxmarl']['env_steps_per_s'] * batch:,.1f} µs/step,"
                    f" ocv2 {1e6 / row['ocv2']['env_steps_per_s'] * batch:,.1f} µs/step"
                )
        if ref:
            out += ["From the main sweep, for reference: " + "; ".join(ref) + ".", ""]
    out.append(END_MARK)
    return "\n".join(out)


# ---------------------------------------------------------------------------- main
def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--layouts", nargs="+", default=None, help=f"default: {' '.join(DEFAULT_LAYOUTS)}")
    p.add_argument(
        "--views", nargs="+", default=None, help="agent_view_size values, 'none' = full grid (default: none 2)"
    )
    p.add_argument("--batches", nargs="+", type=int, default=None, help="default: 1 64 1024")
    p.add_argument("--steps", type=int, default=256, help="env steps per timed scan")
    p.add_argument("--repeats", type=int, default=3, help="least timed runs per case per round")
    p.add_argument(
        "--min-time",
        type=float,
        default=0.5,
        help="least seconds of timed runs per case per round: short cases (batch 1) repeat more,"
        " so one noisy moment on a shared machine does not decide their median",
    )
    p.add_argument(
        "--rounds",
        type=int,
        default=None,
        help="interleaved sweeps (default 5; 1 with --quick): the shared VMs this runs on swing by"
        " +-35 %% between minutes, and the median of fewer sweeps lets one slow minute decide a cell",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: one layout (cramped_room), batches 1 and 64, 1 round, small time split",
    )
    p.add_argument("--split-layout", default="grounded_coord_simple", help="layout for 'Where the time goes'")
    p.add_argument(
        "--split-batch", type=int, default=None, help="batch for 'Where the time goes' (default 1024; 64 with --quick)"
    )
    p.add_argument("--no-split", action="store_true", help="skip 'Where the time goes'")
    p.add_argument("--out", default="docs/BENCHMARKS.md", help="Markdown file to write ('' = don't write)")
    p.add_argument("--json", default=None, help="also write all results to this JSON file")
    args = p.parse_args(argv)

    if args.quick:
        args.layouts = args.layouts or ["cramped_room"]
        args.batches = args.batches or [1, 64]
        args.rounds = args.rounds or 1
        args.split_batch = args.split_batch or 64
    args.layouts = args.layouts or DEFAULT_LAYOUTS
    args.views = args.views or DEFAULT_VIEWS
    args.batches = args.batches or DEFAULT_BATCHES
    args.rounds = args.rounds or 5
    args.split_batch = args.split_batch or 1024
    views = [None if str(v).lower() == "none" else int(v) for v in args.views]
    command = "python " + " ".join(
        [os.path.relpath(sys.argv[0]) if sys.argv[0] else "bench/env_throughput.py"]
        + (sys.argv[1:] if argv is None else list(argv))
    )

    t_start = time.perf_counter()
    info = environment_info()
    info.update(steps=args.steps, repeats=args.repeats, min_time=args.min_time, rounds=args.rounds, command=command)
    log("# environment: " + json.dumps(info))

    # ---- main sweep, interleaved
    configs = [(lay, v, b) for lay in args.layouts for v in views for b in args.batches]
    cases: dict[tuple, Case] = {}
    n_total = len(configs) * len(IMPLS)
    for rnd in range(args.rounds):
        order = IMPLS if rnd % 2 == 0 else IMPLS[::-1]
        for ci, cfg in enumerate(configs):
            for impl in order:
                key = (impl,) + cfg
                if key not in cases:
                    cases[key] = Case(impl, *cfg, steps=args.steps)
                case = cases[key]
                new = case.time(case.repeats_for(args.repeats, args.min_time))
                med_new = statistics.median(new)
                log(
                    f"[round {rnd + 1}/{args.rounds} case {ci * len(IMPLS) + order.index(impl) + 1}/{n_total}]"
                    f" {impl:8s} {cfg[0]:22s} view={view_str(cfg[1]):4s} batch={cfg[2]:5d}"
                    f"  this round: {args.steps * cfg[2] / med_new:>12,.0f} env steps/s"
                    f"  (compile+1st {case.compile_s:.1f}s, 2nd {case.second_run_s:.3f}s, {len(new)} runs,"
                    f" min/median/max {min(new):.4f}/{med_new:.4f}/{max(new):.4f}s)"
                )

    rows_by_cfg: dict[tuple, dict] = {}
    for cfg in configs:
        rows_by_cfg[cfg] = {impl: cases[(impl,) + cfg].result() for impl in IMPLS}
    table, summary = results_table(rows_by_cfg, configs)
    # Release the sweep's executables and buffers before the time split.
    cases.clear()
    gc.collect()
    jax.clear_caches()

    # ---- where the time goes (ocv2 only)
    split_results: dict = {}
    split_md = ""
    if not args.no_split:
        import ocv2

        split_cases = {}
        for v in views:
            env = ocv2.make(args.split_layout, agent_view_size=v)
            fns = make_split_fns(env, args.split_batch, args.steps)
            for part, _ in SPLIT_PARTS:
                if part in REFERENCE_PARTS:
                    split_cases[(v, part)] = Case(
                        REFERENCE_PARTS[part], args.split_layout, v, args.split_batch, steps=args.steps
                    )
                else:
                    fn, carry = fns[part]
                    split_cases[(v, part)] = SplitCase(fn, carry)
        for rnd in range(args.rounds):
            for v in views:
                for part, _ in SPLIT_PARTS:
                    sc = split_cases[(v, part)]
                    sc.time(args.repeats)
                    log(
                        f"[split round {rnd + 1}/{args.rounds}] {args.split_layout} view={view_str(v):4s}"
                        f" batch={args.split_batch} {part:13s}"
                        f" {1e6 * statistics.median(sc.times[-args.repeats :]) / args.steps:10,.1f} µs/step"
                    )
        for v in views:
            split_results[v] = {}
            for part, _ in SPLIT_PARTS:
                sc = split_cases[(v, part)]
                med = statistics.median(sc.times)
                split_results[v][part] = {
                    "us_per_step": 1e6 * med / args.steps,
                    "ns_per_env_step": 1e9 * med / args.steps / args.split_batch,
                    "times_s": [round(t, 5) for t in sc.times],
                    "compile_plus_first_run_s": round(sc.compile_s, 3),
                }
        split_md = split_table(split_results, args.split_batch)

    wall_s = time.perf_counter() - t_start
    log("")
    log(table)
    log("")
    log(
        f"Summary: {summary['met']}/{summary['cells']} cells meet the target; ratio min"
        f" {summary['min_ratio']:.2f}x, median {summary['median_ratio']:.2f}x, max {summary['max_ratio']:.2f}x"
    )
    if split_md:
        log("")
        log(f"Where the time goes (ocv2, {args.split_layout}, batch {args.split_batch}):")
        log(split_md)
    log(f"\nwall time: {wall_s:.1f} s ({wall_s / 60:.1f} min)")

    if args.out:
        block = build_markdown(
            info,
            args,
            command,
            table,
            summary,
            split_md,
            (args.split_layout, args.split_batch),
            split_results,
            rows_by_cfg,
            wall_s,
        )
        write_section(args.out, block, START_MARK, END_MARK)
        log(f"wrote {args.out}")
    if args.json:
        payload = {
            "environment": info,
            "wall_s": wall_s,
            "results": [r for cfg in configs for r in rows_by_cfg[cfg].values()],
            "summary": summary,
            "time_split": {
                "layout": args.split_layout,
                "batch": args.split_batch,
                "by_view": {view_str(v): parts for v, parts in split_results.items()},
            },
        }
        with open(args.json, "w") as f:
            json.dump(payload, f, indent=2)
        log(f"wrote {args.json}")


if __name__ == "__main__":
    main()
