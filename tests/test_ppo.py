"""PPO (population/ppo.py): GAE, recurrent replay, schedules, chunking/resume, populations, metrics, FCP.

Everything runs on tiny models (one conv of 4, fc 8, GRU 8) and tiny batches (4 environments x 16 steps).
"""

from __future__ import annotations

import math

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from population import ppo
from population.config import parse_config

NUM_ENVS, NUM_STEPS = 4, 16
# the smallest recurrent net (compile time is what these tests pay for); exact sizes: tests/test_networks.py
SMALL_MODEL = {
    "kind": "rnn",
    "mixer_features": [],
    "conv_features": [4],
    "conv_kernels": [3],
    "fc_dim": 8,
    "gru_dim": 8,
}


def _raw(max_steps: int, **ppo_overrides) -> dict:
    per_update = NUM_ENVS * NUM_STEPS
    return {
        "env": {"layout": "cramped_room", "max_steps": max_steps},
        "model": dict(SMALL_MODEL),
        "ppo": {
            "num_envs": NUM_ENVS,
            "num_steps": NUM_STEPS,
            "num_minibatches": 2,
            "update_epochs": 2,
            "total_timesteps": 8 * per_update,
            "rew_shaping_horizon": 4 * per_update,
            **ppo_overrides,
        },
    }


def _config(max_steps: int, population: dict | None = None, **ppo_overrides):
    raw = _raw(max_steps, **ppo_overrides)
    if population:
        raw["population"] = population
    return parse_config(raw)


def _leaves_equal(a, b) -> bool:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    return all(
        np.array_equal(np.asarray(x), np.asarray(y), equal_nan=np.issubdtype(np.asarray(x).dtype, np.floating))
        for x, y in zip(la, lb)
    )


def _assert_trees_close(a, b, rtol=1e-6, atol=1e-7):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def _single(trainer, seed: int, pool_size: int = 0):
    return ppo.take_seed(ppo.init_population(trainer, [seed], pool_size=pool_size), 0)


@pytest.fixture(scope="module")
def trainer():
    # max_steps 20 > num_steps 16: no episode ends in the first update, one ends in each later update
    return ppo.make_trainer(_config(max_steps=20))


@pytest.fixture(scope="module")
def inits(trainer):
    """Initial states: seed 3 alone and seeds [1, 3, 5] together (``init_population`` compiles once per trainer)."""
    return ppo.init_population(trainer, [3]), ppo.init_population(trainer, [1, 3, 5])


@pytest.fixture(scope="module")
def seed3(inits):
    return ppo.take_seed(inits[0], 0)


# ---------------------------------------------------------------------------------------------------
# GAE
# ---------------------------------------------------------------------------------------------------


def test_compute_gae_matches_a_hand_computation():
    gamma, lam = 0.9, 0.8
    rewards = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 0.0], [0.0, 1.0], [1.0, -1.0]], np.float32)
    values = np.array([[0.5, 0.1], [0.2, 0.4], [0.3, -0.2], [0.7, 0.6], [0.1, 0.3]], np.float32)
    terminals = np.zeros((5, 2), bool)
    terminals[2, 0] = True  # environment 0's episode ends in the middle
    terminals[1, 1] = True
    last_value = np.array([0.9, -0.4], np.float32)

    expected_adv = np.zeros((5, 2))
    for b in range(2):
        gae = 0.0
        for t in reversed(range(5)):
            next_value = last_value[b] if t == 4 else values[t + 1, b]
            not_done = 0.0 if terminals[t, b] else 1.0
            delta = rewards[t, b] + gamma * next_value * not_done - values[t, b]
            gae = delta + gamma * lam * not_done * gae
            expected_adv[t, b] = gae
    adv, targets = ppo.compute_gae(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(terminals), jnp.asarray(last_value), gamma, lam
    )
    np.testing.assert_allclose(adv, expected_adv, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(targets, expected_adv + values, rtol=1e-5, atol=1e-6)
    # the terminal step does not bootstrap: its advantage is r - V
    np.testing.assert_allclose(adv[2, 0], rewards[2, 0] - values[2, 0], rtol=1e-6)
    # spot value computed by hand: env 0, step 4 (last): 1 + 0.9 * 0.9 - 0.1
    np.testing.assert_allclose(adv[4, 0], 1.0 + 0.9 * 0.9 - 0.1, rtol=1e-6)


# ---------------------------------------------------------------------------------------------------
# recurrent replay (JaxMARL PR #191 / jax-aht PR #115)
# ---------------------------------------------------------------------------------------------------


def _rollout(trainer, state, pool_params=None, coef=1.0, length=NUM_STEPS):
    """Scan ``rollout_step`` as ``update_step`` does; also records the state each step started from."""

    def step(carry, x):
        before = carry.state
        carry, transition = ppo.rollout_step(trainer, pool_params, None, carry, x)
        return carry, (transition, before.partner, before.obs, before.start)

    carry, out = jax.lax.scan(step, ppo.StepCarry(state, jnp.float32(coef)), None, length=length)
    return carry.state, out


def _sharpen_policy(params, factor=100.0):
    """Scale the policy head so log-probabilities depend visibly on the GRU state."""
    return jax.tree_util.tree_map_with_path(
        lambda path, x: x * factor if "['params']['Dense_1']" in jax.tree_util.keystr(path) else x, params
    )


def _replay_log_prob(network, params, hidden, batch, reset):
    """Replay a stored rollout from its initial carry with the given reset flags: log-probs [T, B]."""
    _, logits, _ = network.apply(params, hidden, batch.obs, reset)
    return jnp.take_along_axis(jax.nn.log_softmax(logits), batch.action[..., None], axis=-1)[..., 0]


_replay_jit = jax.jit(_replay_log_prob, static_argnums=0)


def _loss_info(trainer, params, hidden, batch):
    adv, targets = ppo.compute_gae(
        batch.reward, batch.value, batch.terminal, jnp.zeros(batch.value.shape[1]), 0.99, 0.95
    )
    return ppo.ppo_loss(trainer, params, hidden, batch, adv, targets)[1]


@pytest.fixture(scope="module")
def replay_setup(trainer, seed3):
    state = seed3.replace(params=_sharpen_policy(seed3.params))
    roll = jax.jit(lambda s: _rollout(trainer, s))
    first, _ = roll(state)  # the second rollout starts mid-episode (step 16 of 20) from a non-zero carry
    initial_hidden = first.hidden
    last, (batch, _, _, _) = roll(first)
    return trainer, first.params, initial_hidden, batch, last


def test_replay_reproduces_the_rollout_log_probs(replay_setup):
    trainer, params, initial_hidden, batch, last = replay_setup
    assert float(jnp.abs(initial_hidden).max()) > 0.0
    # the episode (max_steps 20) ends inside the rollout: the stored reset flag is the previous step's terminal
    assert batch.terminal.any() and batch.reset.any()
    np.testing.assert_array_equal(batch.reset[1:], batch.terminal[:-1])
    assert not bool(batch.reset[0].any())
    assert batch.obs.shape == (NUM_STEPS, NUM_ENVS * 2) + trainer.env.obs_shape

    log_prob = _replay_jit(trainer.network, params, initial_hidden, batch, ppo.replay_reset(trainer.config, batch))
    np.testing.assert_allclose(log_prob, batch.log_prob, atol=1e-5)
    ratio = jnp.exp(log_prob - batch.log_prob)
    np.testing.assert_allclose(ratio, 1.0, atol=1e-4)
    info = jax.jit(_loss_info, static_argnums=0)(trainer, params, initial_hidden, batch)  # ppo_loss's own replay
    assert abs(float(info.approx_kl)) < 1e-8
    assert float(info.clip_frac) == 0.0
    # the policy is not uniform, so a wrong replay could not match by accident
    assert float(batch.log_prob.std()) > 0.05


def test_paper_done_bug_replay_differs_after_episode_boundaries(replay_setup):
    trainer, params, initial_hidden, batch, _ = replay_setup
    buggy = ppo.make_trainer(_config(max_steps=20, paper_done_bug=True))
    np.testing.assert_array_equal(ppo.replay_reset(buggy.config, batch), batch.terminal)
    np.testing.assert_array_equal(ppo.replay_reset(trainer.config, batch), batch.reset)
    log_prob = _replay_jit(buggy.network, params, initial_hidden, batch, ppo.replay_reset(buggy.config, batch))
    diff = np.abs(np.asarray(log_prob - batch.log_prob))
    after_boundary = np.asarray(batch.reset)
    assert after_boundary.any()
    assert diff[after_boundary].max() > 1e-3
    # before the first boundary the replay still agrees
    first_terminal = int(np.argmax(np.asarray(batch.terminal).any(axis=1)))
    assert first_terminal > 0
    assert diff[:first_terminal].max() < 1e-5


# ---------------------------------------------------------------------------------------------------
# schedules
# ---------------------------------------------------------------------------------------------------


def test_lr_schedule_warmup_cosine_and_constant():
    lr = 1e-3
    config = _config(max_steps=20, lr=lr, total_timesteps=100 * NUM_ENVS * NUM_STEPS)
    total = 100 * 2 * 2  # updates x epochs x minibatches
    warmup = int(0.05 * total)
    assert warmup == 20
    schedule = ppo.lr_schedule(config)
    assert float(schedule(0)) == 0.0
    np.testing.assert_allclose(schedule(warmup // 2), lr / 2, rtol=1e-5)
    np.testing.assert_allclose(schedule(warmup), lr, rtol=1e-6)
    assert float(schedule(warmup - 1)) < lr and float(schedule(warmup + 1)) < lr
    decay = total - warmup
    np.testing.assert_allclose(schedule(warmup + decay // 2), lr / 2, rtol=1e-5)
    np.testing.assert_allclose(schedule(warmup + decay // 4), lr * (1 + math.cos(math.pi / 4)) / 2, rtol=1e-5)
    np.testing.assert_allclose(schedule(total), 0.0, atol=1e-9)
    assert float(schedule(total - 1)) < 1e-3 * lr

    constant = ppo.lr_schedule(_config(max_steps=20, lr=lr, anneal_lr=False))
    for step in (0, 1, 20, 200, 10_000):
        assert float(constant(step)) == pytest.approx(lr)


def test_shaping_coef_anneals_linearly():
    config = _config(max_steps=20, rew_shaping_horizon=1000)
    assert float(ppo.shaping_coef(config, 0)) == 1.0
    assert float(ppo.shaping_coef(config, 500)) == pytest.approx(0.5)
    assert float(ppo.shaping_coef(config, 250)) == pytest.approx(0.75)
    assert float(ppo.shaping_coef(config, 1000)) == 0.0
    assert float(ppo.shaping_coef(config, 5000)) == 0.0
    off = _config(max_steps=20, rew_shaping_horizon=0)
    assert float(ppo.shaping_coef(off, 0)) == 0.0


# ---------------------------------------------------------------------------------------------------
# chunking, resume, populations, metrics
# ---------------------------------------------------------------------------------------------------


def _copy(tree):
    return jax.tree.map(jnp.copy, tree)  # the population runner donates its input


@pytest.fixture(scope="module")
def run2(trainer):
    return ppo.make_advance_population(trainer, 2)


@pytest.fixture(scope="module")
def four_updates(trainer, inits):
    return ppo.make_advance_population(trainer, 4)(_copy(inits[0]), None, None)


@pytest.fixture(scope="module")
def two_updates(run2, inits):
    return run2(_copy(inits[0]), None, None)


def test_chunked_equals_unchunked(run2, inits, four_updates, two_updates):
    state4, metrics4 = four_updates
    state2, metrics2a = two_updates
    state22, metrics2b = run2(_copy(state2), None, None)
    metrics22 = jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=1), metrics2a, metrics2b)
    assert int(state22.update[0]) == int(state4.update[0]) == 4
    # exact: the same ops in the same order, only the scan is cut in two
    assert _leaves_equal(state22.params, state4.params)
    assert _leaves_equal(state22, state4)
    assert _leaves_equal(metrics22, metrics4)
    # and training did something
    assert not _leaves_equal(state4.params, inits[0].params)


def test_save_restore_continues_bit_for_bit(run2, inits, four_updates, two_updates):
    state4, metrics4 = four_updates
    state2, _ = two_updates
    blob = flax.serialization.to_bytes(state2)
    template = jax.tree.map(jnp.zeros_like, inits[0])  # every leaf must come from the bytes
    restored = flax.serialization.from_bytes(template, blob)
    assert _leaves_equal(restored, state2)
    state, metrics = run2(restored, None, None)
    assert _leaves_equal(state, state4)
    assert _leaves_equal(metrics, jax.tree.map(lambda x: x[:, 2:], metrics4))


def test_traced_count_chunks_equal_the_scan(trainer, inits, four_updates, monkeypatch, fresh_programs):
    """``make_advance_chunks`` (one program, the count traced) gives the scan's numbers for any cut.

    Chunks of 3 then 1 update and of 1 then 3, all through one program of at most 3 updates, equal the
    4-update ``lax.scan`` of ``make_advance_population`` bit for bit: the same update steps, the same key
    flow; only the loop around them differs. The padding rows past each count are zeros.
    """
    state4, metrics4 = four_updates
    traces = []
    advance_upto = ppo.advance_upto

    def counted(*args, **kwargs):
        traces.append(args[2])
        return advance_upto(*args, **kwargs)

    monkeypatch.setattr(ppo, "advance_upto", counted)  # runs at each trace of the program
    chunks = ppo.make_advance_chunks(trainer, 3)
    for cut in ((3, 1), (1, 3)):
        state, pieces = _copy(inits[0]), []
        for count in cut:
            state, metrics = chunks(state, None, None, np.int32(count))
            pieces.append(jax.tree.map(lambda x, n=count: x[:, :n], metrics))
            assert all(not np.any(np.asarray(x)[:, count:]) for x in jax.tree.leaves(metrics))
        joined = jax.tree.map(lambda *xs: jnp.concatenate(xs, axis=1), *pieces)
        assert _leaves_equal(state, state4), cut
        assert _leaves_equal(joined, metrics4), cut
    assert len(traces) == 1  # four calls, three counts, one program
    with pytest.raises(ValueError, match="at least 1"):
        ppo.make_advance_chunks(trainer, 0)


def test_seed_alone_equals_seed_in_a_batch(run2, inits, two_updates):
    alone_init, batch_init = inits
    assert _leaves_equal(ppo.take_seed(alone_init, 0), ppo.take_seed(batch_init, 1))
    assert not _leaves_equal(ppo.take_seed(batch_init, 0).params, ppo.take_seed(batch_init, 1).params)
    alone, alone_metrics = two_updates
    batch, batch_metrics = run2(_copy(batch_init), None, None)
    alone, batch = ppo.take_seed(alone, 0), ppo.take_seed(batch, 1)
    alone_metrics, batch_metrics = ppo.take_seed(alone_metrics, 0), ppo.take_seed(batch_metrics, 1)
    # Not bit-exact: XLA:CPU picks different matmul kernels for a vmap batch of 1 and of 3, which moves
    # float rounding (max |diff| ~3e-8 after two updates). The trajectories themselves are identical.
    _assert_trees_close(alone.params, batch.params, rtol=1e-6, atol=1e-7)
    _assert_trees_close(alone_metrics, batch_metrics, rtol=1e-5, atol=1e-7)
    for field in ("env_state", "obs", "start", "key", "update", "stats"):
        assert _leaves_equal(getattr(alone, field), getattr(batch, field)), field
    np.testing.assert_array_equal(alone_metrics.episodes, batch_metrics.episodes)


def test_metrics(trainer, four_updates):
    _, m = ppo.take_seed(four_updates, 0)
    per_update = NUM_ENVS * NUM_STEPS
    np.testing.assert_array_equal(m.update, [1, 2, 3, 4])
    np.testing.assert_array_equal(m.env_steps, per_update * np.arange(1, 5))
    # episodes of 20 steps: none ends in update 1 (steps 0-15), one per env in each of updates 2-4
    np.testing.assert_array_equal(m.episodes, [0, NUM_ENVS, NUM_ENVS, NUM_ENVS])
    assert np.isnan(m.sparse_return[0]) and np.isnan(m.shaped_return[0])
    assert np.all(np.isnan(np.asarray(m.recipe_returns[0])))
    assert np.all(np.isfinite(np.asarray(m.sparse_return[1:])))
    assert np.all(np.isfinite(np.asarray(m.shaped_return[1:])))
    assert m.recipe_returns.shape == (4, trainer.recipe_codes.shape[0])
    assert np.any(np.isfinite(np.asarray(m.recipe_returns[1])))
    # shaping anneals over 4 updates' worth of steps, evaluated before each update
    np.testing.assert_allclose(m.shaping_coef, [1.0, 0.75, 0.5, 0.25])
    opt_steps = 2 * 2
    expected_lr = [float(trainer.lr_schedule(u * opt_steps)) for u in range(4)]
    np.testing.assert_allclose(m.lr, expected_lr, rtol=1e-6)
    assert m.loss.total.shape == (4,)
    assert np.all(np.isfinite(np.asarray(m.loss.total)))
    assert np.all(np.asarray(m.loss.entropy) > 0)


def test_episode_returns_are_the_rewards_of_the_episode_summed(trainer, seed3):
    """The returns the metrics average (EpisodeStats) against the rollout's own per-step rewards, summed here."""
    episodes, length = 20, 20  # max_steps 20: every environment ends an episode every 20 steps

    def step(carry, _):
        carry, transition = ppo.rollout_step(trainer, None, None, carry, None)
        stats = carry.state.stats
        return carry, (transition, stats.last_sparse + stats.last_shaped)

    run = jax.jit(
        lambda state: jax.lax.scan(step, ppo.StepCarry(state, jnp.float32(1.0)), None, length=episodes * length)
    )
    _, (transitions, reported) = run(_copy(seed3))
    terminal = np.asarray(transitions.terminal).reshape(episodes, length, NUM_ENVS, 2)
    assert terminal[:, -1].all() and not terminal[:, :-1].any()
    # shaping weight 1: each agent's reward is the team's sparse reward plus its own shaped reward
    rewards = np.asarray(transitions.reward).reshape(episodes, length, NUM_ENVS, 2).mean(axis=3)
    summed = rewards.sum(axis=1)  # [episodes, envs]
    assert (summed > 0).sum() >= 2  # the untrained policy now and then picks up and places an item
    np.testing.assert_allclose(np.asarray(reported).reshape(episodes, length, NUM_ENVS)[:, -1], summed, rtol=1e-6)


# ---------------------------------------------------------------------------------------------------
# FCP
# ---------------------------------------------------------------------------------------------------

POOL_SIZE = 3


@pytest.fixture(scope="module")
def fcp_setup(inits):
    pool = inits[1].params  # seeds 1, 3, 5: three different frozen partners
    fcp = ppo.make_trainer(_config(max_steps=6, population={"method": "fcp"}))
    assert fcp.fcp and fcp.num_sequences == NUM_ENVS
    state = _single(fcp, 0, pool_size=POOL_SIZE)
    length = 3 * 6  # three episodes
    final, (batch, partners, obs, start) = jax.jit(lambda s, p: _rollout(fcp, s, p, length=length))(state, pool)
    return fcp, pool, state, final, batch, partners, obs, start


def test_fcp_partners_are_redrawn_exactly_at_episode_ends(fcp_setup):
    fcp, _, state, _, batch, partners, _, start = fcp_setup
    slot, seat, start = np.asarray(partners.slot), np.asarray(partners.learner_seat), np.asarray(start)
    group = -(-NUM_ENVS // POOL_SIZE)
    assert slot.shape == seat.shape == (18, NUM_ENVS)
    assert slot.min() >= 0 and slot.max() < POOL_SIZE * group
    for t in range(slot.shape[0]):
        assert len(set(slot[t].tolist())) == NUM_ENVS, f"slots not distinct at step {t}: {slot[t]}"
    np.testing.assert_array_equal(start, np.asarray(batch.reset))
    boundaries = [t for t in range(1, slot.shape[0]) if start[t].all()]
    assert boundaries == [6, 12]
    for t in range(1, slot.shape[0]):
        if t in boundaries:
            changed = (slot[t] != slot[t - 1]) | (seat[t] != seat[t - 1])
            assert changed.any(), f"no partner redrawn at the episode boundary {t}"
        else:
            np.testing.assert_array_equal(slot[t], slot[t - 1])
            np.testing.assert_array_equal(seat[t], seat[t - 1])
    assert set(seat.ravel().tolist()) == {0, 1}
    # every pool member gets played
    assert set((slot // group).ravel().tolist()) == set(range(POOL_SIZE))


def test_fcp_learner_sees_its_own_seat(fcp_setup):
    fcp, _, _, _, batch, partners, obs, _ = fcp_setup
    seat = np.asarray(partners.learner_seat)
    obs = np.asarray(obs)  # [T, E, N, ...]
    assert batch.obs.shape == (18, NUM_ENVS) + fcp.env.obs_shape
    expected = obs[np.arange(18)[:, None], np.arange(NUM_ENVS)[None, :], seat]
    np.testing.assert_array_equal(np.asarray(batch.obs), expected)
    other = obs[np.arange(18)[:, None], np.arange(NUM_ENVS)[None, :], 1 - seat]
    assert not np.array_equal(np.asarray(batch.obs), other)  # the two seats' views really differ


_partner_actions_jit = jax.jit(ppo.partner_actions, static_argnums=0)


@pytest.mark.parametrize("t", [6, 9])  # an episode's first step (carry reset) and a mid-episode step
def test_fcp_grouped_partner_actions_equal_per_env_computation(fcp_setup, t):
    fcp, pool, _, _, _, partners, obs, start = fcp_setup
    network = fcp.network
    group = -(-NUM_ENVS // POOL_SIZE)
    partner = jax.tree.map(lambda x: x[t], partners)
    obs_t, start_t = obs[t], start[t]
    if t == 9:
        assert float(jnp.abs(partner.hidden).max()) > 0  # the partner carry is in play
    key = jax.random.PRNGKey(42)
    actions, hidden = _partner_actions_jit(network, pool, partner, obs_t, start_t, key)

    apply = _jitted_apply(network)
    ref_hidden, ref_logits = [], []
    for e in range(NUM_ENVS):  # each environment on its own, with its own partner's parameters
        member = int(partner.slot[e]) // group
        seat = int(partner.learner_seat[e])
        args = (partner.hidden[e : e + 1], obs_t[e, 1 - seat][None, None], start_t[e][None, None])
        h, logits, _ = apply(ppo.take_seed(pool, member), *args)
        ref_hidden.append(h[0])
        ref_logits.append(logits[0, 0])
        if e == 0:  # another member's parameters would give another carry
            h_wrong, _, _ = apply(ppo.take_seed(pool, (member + 1) % POOL_SIZE), *args)
            assert float(jnp.abs(h_wrong - h).max()) > 1e-4
    np.testing.assert_allclose(hidden, jnp.stack(ref_hidden), atol=1e-6)
    # actions: the same per-slot noise over the [K, G] slot grid, each env's row holding its own logits
    grid = jnp.zeros((POOL_SIZE * group, 6)).at[partner.slot].set(jnp.stack(ref_logits))
    ref_actions = jax.random.categorical(key, grid.reshape(POOL_SIZE, group, 6)).reshape(-1)[partner.slot]
    np.testing.assert_array_equal(actions, ref_actions)


_APPLY = {}


def _jitted_apply(network):
    """One jitted ``network.apply`` per network (compiled once for the [1, 1] per-env shapes)."""
    if network not in _APPLY:
        _APPLY[network] = jax.jit(network.apply)
    return _APPLY[network]
