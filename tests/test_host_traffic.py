"""What crosses from the device to the host: nothing inside a training chunk or a cross-play block.

A training chunk (``ppo.make_advance_chunks``, what ``SeedShard.advance`` runs between two stops) and a
cross-play block (one jitted call of ``population.xp.cross_play``: a seat-0 policy with every partner, at
most 64 episodes) are one device program each; the host reads the results once the program is done
(metrics and checkpoints per chunk, returns and start recipes per block, whole trajectories per block only
when an archive asks for them). Nothing inside them may talk to the host: no ``jax.debug.callback`` or
``jax.debug.print``, ``pure_callback``, ``io_callback``, host send/recv, infeed/outfeed or host-memory
offload.

How this is checked. ``jax.transfer_guard_device_to_host("disallow")`` makes an implicit device-to-host copy
an error on a GPU, but on the CPU backend (jaxlib 0.10.2, what CI runs) device memory is host memory and the
guard never fires: not for ``np.asarray`` of a jax array, ``jax.device_get`` or ``float(x)`` (checked), and
on no backend for a Python callback inside a program. So the tests (1) run a real chunk and block under the
guard -- the check on a GPU, a statement of the contract on a CPU -- and (2) inspect the StableHLO that JAX
lowers each program to for every construct that moves data to the host from inside a program (a backend
independent check, the honest CPU equivalent). A positive control shows that (2) catches a
``jax.debug.print`` put into the training step.
"""

from __future__ import annotations

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cluster.runtime import runstate
from cluster.runtime.shard import SeedShard
from population import ppo, xp
from population.config import load_config
from population.evaluation import PairEpisodes

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")

# What a program uses to reach the host from inside: Python callbacks (jax.debug.callback/print,
# pure_callback, io_callback lower to custom calls named xla_[ffi_]python_{cpu,gpu}_callback), host
# send/recv (host callbacks of older JAX, host_callback), infeed/outfeed, and buffers placed in host memory.
_HOST_OPS = re.compile(
    r"custom_call @\w*callback\w*|stablehlo\.(?:send|recv|infeed|outfeed)\b|\b(?:un)?pinned_host\b|host_callback"
)


def host_traffic(lowered) -> list[str]:
    """The host-reaching constructs in a lowered program (``jax.jit(f).lower(...)``): [] when it has none."""
    return sorted(set(_HOST_OPS.findall(lowered.as_text())))


def _stacked(tree, size: int):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct((size,) + tuple(x.shape), x.dtype), tree)


def _chunk_lowering(config, seeds: int = 2):
    """The shard's training program for ``config``, lowered for abstract arguments (nothing is computed)."""
    trainer = ppo.make_trainer(config)
    per_seed = config.population.fcp.per_seed
    pool_size = 2 if trainer.fcp else 0
    states = _stacked(runstate.state_template(trainer, pool_size), seeds)
    buffer = None
    if config.population.method == "sa":
        buffer = _stacked(jax.eval_shape(trainer.env.reset_state, jax.random.PRNGKey(0)), 8)
    pool = None
    if trainer.fcp:
        pool = _stacked(runstate.params_template(trainer), pool_size)
        pool = _stacked(pool, seeds) if per_seed else pool
    program = ppo.make_advance_chunks(trainer, runstate.Schedule.of(config).longest_chunk, per_seed)
    return program.lower(states, buffer, pool, jax.ShapeDtypeStruct((), jnp.int32))


def test_the_check_finds_a_print_in_the_training_step(monkeypatch, fresh_programs):
    update_step = ppo.update_step

    def printing(trainer, pool_params, buffer, state, unused):
        jax.debug.print("update {}", state.update)
        return update_step(trainer, pool_params, buffer, state, unused)

    monkeypatch.setattr(ppo, "update_step", printing)
    assert any("callback" in op for op in host_traffic(_chunk_lowering(load_config(SMOKE))))


@pytest.mark.parametrize(
    "overrides",
    [[], ["population.method=sa"], ["population.method=fcp", "population.fcp.pool=per_seed", "model.kind=rnn"]],
    ids=["sp", "sa", "fcp_per_seed_rnn"],
)
def test_a_training_chunk_has_no_host_traffic(overrides):
    assert host_traffic(_chunk_lowering(load_config(SMOKE, overrides))) == []


def test_a_training_chunk_runs_under_the_transfer_guard(tmp_path, monkeypatch):
    """The shard's real chunks (2 + 2 updates) under ``transfer_guard_device_to_host("disallow")``; the
    metrics and checkpoints are read after each chunk, outside it."""
    config = load_config(SMOKE)
    counts = []
    original = ppo.make_advance_chunks

    def guarded(trainer, max_updates, pool_per_seed=False):
        program = original(trainer, max_updates, pool_per_seed)

        def run(states, buffer, pool, count):
            counts.append(int(count))
            with jax.transfer_guard_device_to_host("disallow"):
                return jax.block_until_ready(program(states, buffer, pool, count))

        return run

    monkeypatch.setattr(ppo, "make_advance_chunks", guarded)
    shard = SeedShard(config, tmp_path / "run", [0, 1])
    result = shard.advance(config.ppo.num_updates)
    assert counts == [2, 2] and result.update == config.ppo.num_updates
    assert sorted({r["update"] for r in result.rows}) == [1, 2, 3, 4]


@pytest.fixture(scope="module")
def policies():
    config = load_config(SMOKE)
    trainer = ppo.make_trainer(config)
    return trainer, ppo.eval_env(config), ppo.init_population(trainer, [0, 1]).params


@pytest.mark.parametrize("archive", [False, True], ids=["scores", "archive"])
def test_a_cross_play_block_has_no_host_traffic_and_is_copied_once(policies, monkeypatch, archive):
    """Without an archive a block's program returns only returns and start recipes [partners, episodes]
    (what matrix.csv, episodes.csv and summary.json need); with one, every transition of the block, read
    once per block (``on_block``), never per step."""
    trainer, env, params = policies
    name = "jitted_play_recorded_row" if archive else "_jitted_play"
    original = getattr(xp, name)
    lowered, shapes = [], []

    def build(*args):
        program = original(*args)

        def run(seat0, cols, key):
            if not lowered:
                lowered.append(program.lower(seat0, cols, key))
                shapes.append(jax.eval_shape(program, seat0, cols, key))
            with jax.transfer_guard_device_to_host("disallow"):
                return jax.block_until_ready(program(seat0, cols, key))

        return run

    monkeypatch.setattr(xp, name, build)
    blocks = []
    on_block = (lambda row, first, recorded: blocks.append((row, first, recorded.actions.shape))) if archive else None
    episodes = 3
    result = xp.cross_play(
        trainer.network.apply,
        runstate.hidden_size(trainer),
        env,
        params,
        jax.random.PRNGKey(0),
        episodes,
        on_block=on_block,
    )
    assert result.returns.shape == (2, 2, episodes) and not np.isnan(result.returns).any()
    assert host_traffic(lowered[0]) == []
    if archive:  # one call per row and block, each holding every step of the block's episodes
        assert blocks == [(0, 0, (2, episodes, env.max_steps, 2)), (1, 0, (2, episodes, env.max_steps, 2))]
    else:
        assert isinstance(shapes[0], PairEpisodes) and shapes[0].states is None
        assert [(x.shape, x.dtype) for x in jax.tree.leaves(shapes[0])] == [
            ((2, episodes), jnp.float32),
            ((2, episodes), jnp.int32),
        ]
