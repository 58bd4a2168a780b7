"""Population methods as pure functions (no run directories): SA buffers, OP environments, cross-play of
hand-made policies, the cross-play summary and checkpoints.

Tiny sizes throughout (configs/smoke.yaml: cramped_room, 40-step episodes, a [8, 8] CNN).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

import ocv2
from ocv2.items import Action, Static, ingredient_unit, recipe_encoding_np
from population import checkpoints as ckpt
from population import ppo
from population.config import load_config
from population.evaluation import play_episodes, stack_params
from population.sa import all_pairs, buffer_size, collect_buffer, collect_pair_states, merge_buffers
from population.xp import CrossPlay, bootstrap_block, cross_play, summarize

SMOKE = Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml"


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def _assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(_leaves(a), _leaves(b), strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def _take(tree, index):
    return jax.tree.map(lambda x: x[index], tree)


def _same_kitchen(a, b) -> bool:
    """Same grid, agents (position, facing, inventory) and recipe."""
    return all(
        np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in (
            (a.grid, b.grid),
            (a.recipe, b.recipe),
            (a.agents.x, b.agents.x),
            (a.agents.y, b.agents.y),
            (a.agents.dir, b.agents.dir),
            (a.agents.inventory, b.agents.inventory),
        )
    )


def _matching_entries(state, buffer) -> list[int]:
    return [i for i in range(int(buffer.step.shape[0])) if _same_kitchen(state, _take(buffer, i))]


# ---------------------------------------------------------------------------------------------------
# SA: the reset buffer (two untrained CNN policies on the smoke config)
# ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sa_setup():
    config = load_config(SMOKE, ["population.method=sa"])
    trainer = ppo.make_trainer(config)
    states = ppo.init_population(trainer, [0, 1])
    env = ppo.eval_env(config)
    key = jax.random.PRNGKey(42)
    apply, hidden = trainer.network.apply, 0  # the CNN has no carry
    sa = config.population.sa
    whole = collect_pair_states(apply, hidden, env, states.params, key, sa)
    buffer = collect_buffer(apply, hidden, env, states.params, key, sa)
    # The same pairs split over two calls, each in a shuffled order.
    part_a = collect_pair_states(apply, hidden, env, states.params, key, sa, pairs=[(1, 1), (0, 0)])
    part_b = collect_pair_states(apply, hidden, env, states.params, key, sa, pairs=[(1, 0), (0, 1)])
    return dict(
        config=config,
        trainer=trainer,
        states=states,
        env=env,
        sa=sa,
        whole=whole,
        buffer=buffer,
        parts=(part_a, part_b),
    )


def test_sa_buffer_holds_every_ordered_pair_at_the_kept_steps(sa_setup):
    sa, whole, buffer = sa_setup["sa"], sa_setup["whole"], sa_setup["buffer"]
    max_steps = sa_setup["env"].max_steps
    assert (max_steps, sa.rollouts_per_pair, sa.keep_every) == (40, 2, 10)  # the sizes below assume smoke.yaml
    assert buffer_size(2, sa, max_steps) == 2 * 2 * 2 * 4
    assert int(buffer.step.shape[0]) == buffer_size(2, sa, max_steps)
    for leaf in jax.tree.leaves(buffer):
        assert leaf.shape[0] == 32

    assert whole.pairs == ((0, 0), (0, 1), (1, 0), (1, 1)) == tuple(all_pairs(2))
    per_pair = sa.rollouts_per_pair * (max_steps // sa.keep_every)  # R * S
    steps = np.asarray(whole.states.step)
    assert steps.shape == (4, per_pair)
    expected_steps = np.tile(np.arange(0, max_steps, sa.keep_every), sa.rollouts_per_pair)  # 0,10,20,30,0,10,..
    for block in steps:
        np.testing.assert_array_equal(block, expected_steps)
    assert not np.asarray(whole.states.done).any()

    # The buffer is the pair blocks in pair order.
    for index, _pair in enumerate(whole.pairs):
        block = _take(buffer, slice(index * per_pair, (index + 1) * per_pair))
        _assert_trees_equal(block, _take(whole.states, index))
    _assert_trees_equal(buffer, merge_buffers([whole]))

    # The kept states are real play: agents have moved away from the layout's start in some of them.
    start = _take(buffer, 0)
    moved = [i for i in range(32) if int(buffer.step[i]) > 0 and not _same_kitchen(_take(buffer, i), start)]
    assert moved


def test_sa_buffer_split_over_calls_merges_to_the_identical_buffer(sa_setup):
    part_a, part_b = sa_setup["parts"]
    assert part_a.pairs == ((1, 1), (0, 0)) and part_b.pairs == ((1, 0), (0, 1))
    # Each pair's states depend only on (key, i, j), not on the call or position it ran in.
    for part in (part_a, part_b):
        for index, pair in enumerate(part.pairs):
            _assert_trees_equal(_take(part.states, index), _take(sa_setup["whole"].states, all_pairs(2).index(pair)))
    _assert_trees_equal(merge_buffers([part_a, part_b]), sa_setup["buffer"])
    _assert_trees_equal(merge_buffers([part_b, part_a]), sa_setup["buffer"])


def test_collect_pair_states_rejects_pairs_out_of_range(sa_setup):
    s = sa_setup
    with pytest.raises(ValueError, match="out of range"):
        collect_pair_states(
            s["trainer"].network.apply, 0, s["env"], s["states"].params, jax.random.PRNGKey(0), s["sa"], pairs=[(0, 2)]
        )


def test_resets_from_the_buffer_reproduce_stored_states(sa_setup):
    env, buffer = sa_setup["env"], sa_setup["buffer"]
    keys = jax.random.split(jax.random.PRNGKey(7), 48)
    drawn = jax.jit(jax.vmap(lambda k: env.reset_state(k, state_buffer=buffer)))(keys)
    nontrivial = 0
    for r in range(48):
        state = _take(drawn, r)
        matches = _matching_entries(state, buffer)
        assert matches, f"reset {r} is not a buffer entry"
        assert int(state.step) == 0 and not bool(state.done) and not bool(state.new_correct_delivery)
        nontrivial += any(int(buffer.step[i]) > 0 for i in matches)
    assert nontrivial > 0  # some draws are mid-episode states, not just the layout's start


def test_restart_episodes_resets_training_envs_from_the_buffer(sa_setup):
    trainer, buffer = sa_setup["trainer"], sa_setup["buffer"]
    state = ppo.take_seed(sa_setup["states"], 1)
    restarted = ppo.restart_episodes(trainer, state, jax.random.PRNGKey(3), buffer)
    num_envs = trainer.config.ppo.num_envs
    nontrivial = 0
    for e in range(num_envs):
        env_state = _take(restarted.env_state, e)
        matches = _matching_entries(env_state, buffer)
        assert matches, f"env {e} does not start from a buffer entry"
        assert int(env_state.step) == 0 and not bool(env_state.done)
        nontrivial += any(int(buffer.step[i]) > 0 for i in matches)
    np.testing.assert_array_equal(
        np.asarray(restarted.obs), np.asarray(jax.vmap(trainer.env.get_obs_arrays)(restarted.env_state))
    )
    assert np.asarray(restarted.start).all()
    # Learning state is kept.
    _assert_trees_equal(restarted.params, state.params)
    _assert_trees_equal(restarted.opt_state, state.opt_state)
    np.testing.assert_array_equal(np.asarray(restarted.update), np.asarray(state.update))
    # 4 draws from 32 entries of which 8 are step-0 states: at least one mid-episode start with this key
    assert nontrivial > 0


# ---------------------------------------------------------------------------------------------------
# OP: permuted observations, unchanged game
# ---------------------------------------------------------------------------------------------------


def _op_config():
    return load_config(SMOKE, ["population.method=op", "env.layout=grounded_coord_simple"])


def test_op_train_env_permutes_and_eval_env_does_not():
    config = _op_config()
    assert ocv2.LAYOUTS["grounded_coord_simple"].num_ingredients >= 2
    assert config.population.op.ingredients == (0, 1)
    train, evaluation = ppo.train_env(config), ppo.eval_env(config)
    assert tuple(train.config.op_ingredient_permutations) == tuple(config.population.op.ingredients)
    assert train.config.op_enabled
    assert evaluation.config.op_ingredient_permutations is None and not evaluation.config.op_enabled
    assert ppo.make_trainer(config).env.config.op_enabled
    # Other methods train without permutations.
    sp = load_config(SMOKE, ["env.layout=grounded_coord_simple"])
    assert not ppo.train_env(sp).config.op_enabled


def _ingredient_channel_blocks(n: int) -> list[int]:
    """Starts of the n-wide ingredient blocks (ocv2/observations.py channel order): ego inventory,
    other agents' inventories, piles, grid items, recipe."""
    return [7, 14 + n, 20 + 2 * n, 22 + 3 * n, 24 + 4 * n]


def test_op_observations_differ_only_in_permuted_ingredient_channels():
    config = _op_config()
    op_env, plain_env = ppo.train_env(config), ppo.eval_env(config)
    n = op_env.config.num_ingredients
    moved = list(config.population.op.ingredients)
    starts = _ingredient_channel_blocks(n)
    ingredient_channels = {s + j for s in starts for j in range(n)}
    channels = op_env.obs_shape[-1]
    assert channels == plain_env.obs_shape[-1] == 25 + 5 * n

    layout = op_env.layout
    pot = np.argwhere(np.asarray(layout.static_objects) == Static.POT)[0]

    @jax.jit
    def views(key):
        state = op_env.reset_state(key)
        # Put ingredients everywhere the observation shows them: both inventories and the pot.
        state = state.replace(
            agents=state.agents.replace(inventory=jnp.asarray([ingredient_unit(0), ingredient_unit(1)], jnp.int32)),
            grid=state.grid.at[pot[0], pot[1], 1].set(ingredient_unit(0) + 2 * ingredient_unit(1)),
        )
        return state.ingredient_permutations, op_env.get_obs_arrays(state), plain_env.get_obs_arrays(state)

    permuted_seen = 0
    for seed in range(6):
        perms, obs_op, obs_plain = (np.asarray(x) for x in views(jax.random.PRNGKey(seed)))
        for agent in range(2):
            perm = perms[agent]
            # Only the configured ingredients move; the rest map to themselves.
            assert sorted(perm[moved]) == moved
            assert all(perm[i] == i for i in range(n) if i not in moved)
            for c in range(channels):
                if c not in ingredient_channels:
                    np.testing.assert_array_equal(obs_op[agent, ..., c], obs_plain[agent, ..., c])
            for start in starts:
                for j in range(n):  # observation slot j shows true ingredient perm[j]
                    np.testing.assert_array_equal(obs_op[agent, ..., start + j], obs_plain[agent, ..., start + perm[j]])
            if not np.array_equal(perm, np.arange(n)):
                permuted_seen += 1
                assert not np.array_equal(obs_op[agent], obs_plain[agent])
            else:
                np.testing.assert_array_equal(obs_op[agent], obs_plain[agent])
    assert permuted_seen > 0  # the check above is not vacuous


def test_op_does_not_change_the_game():
    config = _op_config()
    op_env, plain_env = ppo.train_env(config), ppo.eval_env(config)
    steps = 60

    def trajectory(env, key):
        k_reset, k_act, k_steps = jax.random.split(key, 3)
        state = env.reset_state(k_reset)
        actions = jax.random.randint(k_act, (steps, 2), 0, 6)

        def body(s, x):
            k, a = x
            out = env.step_arrays(k, s, a)
            return out.state, (
                out.state.grid,
                out.state.agents,
                out.state.recipe,
                out.reward,
                out.shaped_reward,
                out.done,
            )

        return state, jax.lax.scan(body, state, (jax.random.split(k_steps, steps), actions))[1]

    keys = jax.random.split(jax.random.PRNGKey(100), 3)
    both = jax.jit(jax.vmap(lambda k: (trajectory(op_env, k), trajectory(plain_env, k))))  # one compile
    (start_op, traj_op), (start_plain, traj_plain) = both(keys)
    for e in range(3):
        assert _same_kitchen(_take(start_op, e), _take(start_plain, e))
    assert not np.array_equal(
        np.asarray(start_op.ingredient_permutations), np.asarray(start_plain.ingredient_permutations)
    )
    _assert_trees_equal(traj_op, traj_plain)


# ---------------------------------------------------------------------------------------------------
# Cross-play of hand-made policies
# ---------------------------------------------------------------------------------------------------

R, D, L, U, S, I = (
    int(Action.RIGHT),
    int(Action.DOWN),
    int(Action.LEFT),
    int(Action.UP),
    int(Action.STAY),
    int(Action.INTERACT),
)
# cramped_room ("WWPWW/OA AO/W   W/WBWXW"): seat 0 starts at (3, 1) facing up, seat 1 at (1, 1).
# Derived by stepping the env by hand; seat 0 cooks and delivers one onion soup alone.
ONION_TRIP = [R, I, L, U, I]  # face the right onion pile, take, step left under the pot, face it, put in
COOK_SCRIPT = (
    ONION_TRIP * 3  # 15 steps: the third onion starts the 20-step cooking
    + [D, L, D, I]  # to (1, 2), face the plate pile below, take a plate
    + [R, U]  # back under the pot, facing it
    + [S] * 14  # wait for the soup
    + [I]  # t = 35: plate the soup
    + [D, R, D, I]
)  # to (3, 2), face the goal below, deliver (t = 39: reward 20)
SCRIPT_STEPS = 48  # env.max_steps for the scripted episodes


def script_apply(params, hidden, obs, reset):
    """Open-loop policy: ``params`` is an int32 action table [T]; the carry [B, 1] counts steps."""
    t = jnp.where(reset[0], 0, hidden[:, 0].astype(jnp.int32))
    action = params[jnp.minimum(t, params.shape[0] - 1)]
    logits = 1e4 * jax.nn.one_hot(action, 6)  # sampling is deterministic
    batch = obs.shape[1]
    return (t + 1).astype(jnp.float32)[:, None], logits[None], jnp.zeros((1, batch), jnp.float32)


def _table(actions) -> np.ndarray:
    return np.asarray(list(actions) + [S] * (SCRIPT_STEPS - len(actions)), np.int32)


_STEP_CACHE = {}


def _replay(env, table_0, table_1) -> float:
    """Independent reference: step the env by hand with the two action tables."""
    step = _STEP_CACHE.setdefault(id(env), jax.jit(env.step_arrays))
    state = env.reset_state(jax.random.PRNGKey(0))
    total = 0.0
    for t in range(env.max_steps):
        out = step(jax.random.PRNGKey(t), state, jnp.asarray([table_0[t], table_1[t]], jnp.int32))
        total += float(out.reward[0])
        state = out.state
    assert bool(out.done)
    return total


@pytest.fixture(scope="module")
def scripted():
    env = ocv2.make("cramped_room", max_steps=SCRIPT_STEPS)
    tables = [_table(COOK_SCRIPT), _table([])]  # [cook, stay]
    params = stack_params([jnp.asarray(t) for t in tables])
    result = cross_play(script_apply, 1, env, params, jax.random.PRNGKey(5), episodes=3)
    return env, tables, params, result


def test_cook_script_scores_one_delivery_with_a_staying_partner(scripted):
    env, tables, _, _ = scripted
    assert len(COOK_SCRIPT) == 40 and env.max_steps == SCRIPT_STEPS
    assert _replay(env, tables[0], tables[1]) == 20.0
    # Through play_episodes (the rollout behind cross-play), seat 0 = cook, seat 1 = stay.
    play = jax.jit(lambda a, b, k: play_episodes(script_apply, 1, env, (a, b), k, 2, keep_every=8))
    result = play(jnp.asarray(tables[0]), jnp.asarray(tables[1]), jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(result.returns), [20.0, 20.0])
    np.testing.assert_array_equal(np.asarray(result.states.step[0]), [0, 8, 16, 24, 32, 40])
    # Seat 0 holds: nothing, an onion (t=8, second trip), nothing (t=16), a plate (t=24, 32), nothing (delivered).
    held = np.asarray(result.states.agents.inventory[0, :, 0])
    np.testing.assert_array_equal(held, [0, ingredient_unit(0), 0, 1, 1, 0])
    assert (np.asarray(result.states.agents.inventory[0, :, 1]) == 0).all()  # the staying partner never holds anything


def test_cross_play_of_scripted_policies(scripted):
    env, tables, _, result = scripted
    assert result.returns.shape == (2, 2, 3) and result.start_recipe.shape == (2, 2, 3)
    matrix = result.matrix
    assert (result.returns == result.returns[..., :1]).all()  # deterministic: every episode alike
    assert matrix[0, 1] == 20.0 * 1  # row = seat 0 (cook), column = seat 1 (stay): one delivery
    assert matrix[1, 1] == 0.0  # nobody cooks
    # Cells whose value depends on both agents moving: equal to the hand-stepped replay of the same pair.
    assert matrix[0, 0] == _replay(env, tables[0], tables[0])
    assert matrix[1, 0] == _replay(env, tables[1], tables[0])
    # The cook script in seat 1 (start (1, 1)) never reaches an onion pile, so it cannot score.
    assert matrix[1, 0] == 0.0
    assert (result.start_recipe == recipe_encoding_np((0, 0, 0))).all()

    summary = summarize(result)
    sp, xp = [matrix[0, 0], matrix[1, 1]], [matrix[0, 1], matrix[1, 0]]
    assert summary["sp_mean"] == pytest.approx(np.mean(sp))
    assert summary["sp_std"] == pytest.approx(np.std(sp, ddof=1))
    assert summary["xp_mean"] == pytest.approx(np.mean(xp)) == pytest.approx(10.0)
    assert summary["xp_std"] == pytest.approx(np.std(xp, ddof=1))
    assert summary["gap"] == pytest.approx(np.mean(sp) - np.mean(xp))
    assert summary["num_policies"] == 2 and summary["episodes_per_pair"] == 3


def test_cross_play_rows_only_fills_those_rows(scripted):
    env, _, params, full = scripted
    result = cross_play(script_apply, 1, env, params, jax.random.PRNGKey(5), episodes=3, rows=[0])
    np.testing.assert_array_equal(result.returns[0], full.returns[0])
    assert np.isnan(result.returns[1]).all()


def test_cross_play_reports_progress_per_block(scripted):
    env, _, params, full = scripted
    calls = []
    result = cross_play(
        script_apply,
        1,
        env,
        params,
        jax.random.PRNGKey(5),
        episodes=3,
        rows=[0, 1],
        on_progress=lambda done, total: calls.append((done, total)),
    )
    np.testing.assert_array_equal(result.returns, full.returns)  # watching does not change the numbers
    assert calls[0] == (0, 2) and calls[1:] == [(1, 2), (1, 2)]  # 2 rows x 1 block of 3 episodes


# ---------------------------------------------------------------------------------------------------
# summarize on a synthetic matrix
# ---------------------------------------------------------------------------------------------------


def test_summarize_synthetic_cross_play():
    rng = np.random.default_rng(0)
    returns = rng.integers(0, 5, size=(3, 3, 4)).astype(np.float32) * 20.0
    recipes = np.where(np.arange(4) % 2 == 0, 12, 48).astype(np.int32) * np.ones((3, 3, 1), np.int32)
    recipes[1, 2, :] = 12  # one cell saw only the first recipe
    result = CrossPlay(returns, recipes)
    summary = summarize(result, {12: "0+0+0", 48: "1+1+1"})

    matrix = returns.mean(-1)
    diagonal = [matrix[i, i] for i in range(3)]
    off = [matrix[i, j] for i in range(3) for j in range(3) if i != j]
    assert len(off) == 6
    assert summary["sp_mean"] == pytest.approx(np.mean(diagonal))
    assert summary["sp_std"] == pytest.approx(np.std(diagonal, ddof=1))
    assert summary["xp_mean"] == pytest.approx(np.mean(off))
    assert summary["xp_std"] == pytest.approx(np.std(off, ddof=1))
    assert summary["gap"] == pytest.approx(np.mean(diagonal) - np.mean(off))
    ci = bootstrap_block(matrix)  # 95 % intervals by bootstrap over seeds; ci95 = their half-widths
    for name in ("sp", "xp"):
        assert summary[f"{name}_ci95_interval"] == pytest.approx(list(ci[name]))
        assert summary[f"{name}_ci95"] == pytest.approx((ci[name][1] - ci[name][0]) / 2)
    assert summary["num_policies"] == 3 and summary["episodes_per_pair"] == 4

    assert set(summary["per_recipe"]) == {"0+0+0", "1+1+1"}
    for code, name in ((12, "0+0+0"), (48, "1+1+1")):
        mask = recipes == code
        sp_cells = [returns[i, i][mask[i, i]].mean() for i in range(3) if mask[i, i].any()]
        xp_cells = [returns[i, j][mask[i, j]].mean() for i in range(3) for j in range(3) if i != j and mask[i, j].any()]
        entry = summary["per_recipe"][name]
        assert entry["episodes"] == int(mask.sum())
        assert entry["sp_mean"] == pytest.approx(np.mean(sp_cells))
        assert entry["xp_mean"] == pytest.approx(np.mean(xp_cells))
    assert summary["per_recipe"]["0+0+0"]["episodes"] == 9 * 2 + 2
    assert summary["per_recipe"]["1+1+1"]["episodes"] == 8 * 2
    # Without names, recipes are keyed by their encoding.
    assert set(summarize(result)["per_recipe"]) == {"12", "48"}


def test_summarize_single_policy_has_no_gap():
    summary = summarize(CrossPlay(np.full((1, 1, 2), 20.0, np.float32), np.zeros((1, 1, 2), np.int32)))
    assert summary["sp_mean"] == 20.0 and summary["sp_std"] == 0.0
    assert math.isnan(summary["xp_mean"]) and math.isnan(summary["gap"])


# ---------------------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def train_state(sa_setup):
    return sa_setup["config"], ppo.take_seed(jax.tree.map(np.asarray, sa_setup["states"]), 1)


def test_checkpoint_round_trip_is_exact(tmp_path, train_state):
    config, state = train_state
    fingerprint = config.fingerprint()
    path = ckpt.checkpoint_path(tmp_path, 3, 17)
    assert path == tmp_path / "checkpoints" / "seed_3" / "update_0000017.msgpack"
    ckpt.save(path, state, fingerprint, seed=3, update=17)
    meta, loaded = ckpt.load(path, state, fingerprint)
    assert meta["fingerprint"] == fingerprint and meta["seed"] == 3 and meta["update"] == 17
    assert meta["version"] == ckpt.FORMAT_VERSION
    assert isinstance(loaded, ppo.TrainState)
    _assert_trees_equal(loaded, state)
    # A shape-only template (as the drivers use) restores the same values.
    template = jax.eval_shape(lambda: state)
    _, from_shapes = ckpt.load(path, template, fingerprint)
    _assert_trees_equal(from_shapes, state)
    # The atomic write leaves only the checkpoint itself.
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert ckpt.list_updates(tmp_path, 3) == [17] and ckpt.latest(tmp_path, 3) == path
    assert ckpt.list_updates(tmp_path, 4) == [] and ckpt.latest(tmp_path, 4) is None


def test_failed_checkpoint_write_keeps_the_previous_file(tmp_path, train_state, monkeypatch):
    config, state = train_state
    path = tmp_path / "update_0000001.msgpack"
    ckpt.save(path, state, config.fingerprint(), update=1)
    before = path.read_bytes()

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("ocv2.atomic.os.replace", fail)  # the rename of the atomic write
    changed = state.replace(update=np.int32(99))
    with pytest.raises(OSError):
        ckpt.save(path, changed, config.fingerprint(), update=99)
    monkeypatch.undo()
    assert path.read_bytes() == before
    _assert_trees_equal(ckpt.load(path, state, config.fingerprint())[1], state)


def test_checkpoint_from_a_different_config_is_refused(tmp_path, train_state):
    config, state = train_state
    path = ckpt.save(tmp_path / "c.msgpack", state, config.fingerprint())
    other = load_config(SMOKE, ["population.method=sa", "ppo.lr=2e-3"]).fingerprint()
    assert other != config.fingerprint()
    with pytest.raises(ckpt.CheckpointError, match="different config"):
        ckpt.load(path, state, other)
    with pytest.raises(ckpt.CheckpointError, match="different config"):
        ckpt.read(path, other)
    # eval/run sections are not part of the fingerprint: their checkpoints stay usable.
    same = load_config(SMOKE, ["population.method=sa", "eval.episodes=9", "run.checkpoint_every=1"])
    assert same.fingerprint() == config.fingerprint()


SMALL_STATE = {"params": {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}, "update": np.int32(80)}
SMALL_META = {"seed": 1, "update": 80, "metrics": [{"update": 80, "return": 12.5}]}  # rows not in metrics.csv yet


def test_any_single_byte_flip_of_a_checkpoint_is_refused(tmp_path):
    """Metadata included: it carries the update number and metric rows a resume relies on."""
    path = ckpt.save(tmp_path / "c.msgpack", SMALL_STATE, "fp", **SMALL_META)
    data = path.read_bytes()
    meta, raw = ckpt.read(path, "fp")
    assert meta["metrics"] == SMALL_META["metrics"] and raw["update"] == 80
    assert b"metrics" in data and b"return" in data  # the metadata is in the file (under the checksum)
    damaged = tmp_path / "damaged.msgpack"
    for offset in range(len(data)):
        for flip in (0x01, 0x20, 0xFF):  # the lowest bit, the ASCII case bit, every bit
            damaged.write_bytes(data[:offset] + bytes([data[offset] ^ flip]) + data[offset + 1 :])
            with pytest.raises(ckpt.CorruptCheckpointError) as error:
                ckpt.read(damaged, "fp")
            assert str(damaged) in str(error.value) and "\n" not in str(error.value)
    damaged.write_bytes(data[:-1])
    with pytest.raises(ckpt.CorruptCheckpointError, match="not a readable"):
        ckpt.read(damaged)


def test_version_2_checkpoints_still_load(tmp_path):
    """The previous format: the state's bytes under a checksum kept in the (unprotected) metadata."""
    state_bytes = serialization.msgpack_serialize(serialization.to_state_dict(SMALL_STATE))
    payload = {
        "meta": {"version": 2, "fingerprint": "fp", "sha256": hashlib.sha256(state_bytes).hexdigest(), **SMALL_META},
        "state": state_bytes,
    }
    path = tmp_path / "v2.msgpack"
    path.write_bytes(serialization.msgpack_serialize(payload))
    meta, state = ckpt.load(path, SMALL_STATE, "fp")
    assert meta["version"] == 2 and meta["metrics"] == SMALL_META["metrics"]
    np.testing.assert_array_equal(state["params"]["w"], SMALL_STATE["params"]["w"])
    payload["state"] = state_bytes[:-1] + bytes([state_bytes[-1] ^ 1])  # its state stays checked
    path.write_bytes(serialization.msgpack_serialize(payload))
    with pytest.raises(ckpt.CorruptCheckpointError, match="checksum mismatch"):
        ckpt.read(path)


@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage", "not_a_checkpoint", "missing"])
def test_unreadable_checkpoints_raise_checkpoint_error(tmp_path, train_state, damage):
    config, state = train_state
    path = ckpt.save(tmp_path / "c.msgpack", state, config.fingerprint())
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "garbage":
        path.write_bytes(bytes(range(256)) * 4)
    elif damage == "not_a_checkpoint":
        from flax import serialization

        path.write_bytes(serialization.msgpack_serialize({"params": np.zeros(3)}))
    else:
        path.unlink()
    with pytest.raises(ckpt.CheckpointError):
        ckpt.load(path, state, config.fingerprint())


def test_checkpoint_with_another_structure_is_refused(tmp_path, train_state):
    config, state = train_state
    path = ckpt.save(tmp_path / "c.msgpack", state, config.fingerprint())
    wrong_shape = state.replace(hidden=np.zeros((5, 3), np.float32))
    with pytest.raises(ckpt.CheckpointError, match="shape"):
        ckpt.load(path, wrong_shape, config.fingerprint())


def test_snapshots():
    assert ckpt.snapshot_updates(610, 3) == [0, 305, 610]
    assert ckpt.snapshot_updates(4, 3) == [0, 2, 4]
    assert ckpt.snapshot_updates(1, 3) == [0, 1]  # duplicates collapse
    snaps = [0, 305, 610]
    assert ckpt.resolve_snapshot("init", snaps) == 0
    assert ckpt.resolve_snapshot("mid", snaps) == 305
    assert ckpt.resolve_snapshot("final", snaps) == 610
    assert ckpt.resolve_snapshot("305", snaps) == 305
    with pytest.raises(ckpt.CheckpointError, match="no snapshot at update 300"):
        ckpt.resolve_snapshot("300", snaps)
