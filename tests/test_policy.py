"""population.policy (``ocv2.policy``) and ``ocv2 export``: loading every kind of source, the export/load
round trip, acting, and one-line errors for bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

from cluster.cli import main
from population import checkpoints as ckpt
from population import policy as pol
from policy_runs import shared_run


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return shared_run(tmp_path_factory)


def _assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


_STEPS = {}


def _act_trace(policy, steps: int = 4, greedy: bool = False):
    """Actions of ``policy`` for both agents over a few env steps (same keys for every policy)."""
    env = policy.make_env()  # one object per settings: the jitted step below is reused
    step = _STEPS.setdefault(id(env), jax.jit(lambda k, s, a: (lambda o: (o.state, o.obs))(env.step_arrays(k, s, a))))
    state = env.reset_state(jax.random.PRNGKey(3))
    obs = env.get_obs_arrays(state)
    hidden, reset, out = policy.initial_hidden(2), jnp.ones((2,), bool), []
    for t in range(steps):
        actions, hidden = policy.act(jax.random.PRNGKey(100 + t), obs, hidden, reset, greedy)
        state, obs = step(jax.random.PRNGKey(t), state, actions)
        reset = jnp.zeros((2,), bool)
        out.append(np.asarray(actions))
    return np.stack(out)


def test_load_accepts_run_seed_dir_and_checkpoint(run):
    by_run = pol.load(run, seed=1)
    by_seed_dir = pol.load(run / "checkpoints" / "seed_1")
    by_file = pol.load(run / "checkpoints" / "seed_1" / "update_0000004.msgpack")
    for other in (by_seed_dir, by_file):
        _assert_trees_equal(by_run.params, other.params)
    assert by_run.meta["update"] == 4 and by_run.hidden_size == 0 and by_run.model.kind == "cnn"
    assert by_run.env == {"layout": "overcookedv2_demo", "max_steps": 100}
    assert pol.load(run, seed=1, checkpoint="mid").meta["update"] == 2
    assert pol.load(run, checkpoint="init").meta["update"] == 0
    assert pol.load(run, checkpoint=2).meta["update"] == 2
    assert pol.load(run, checkpoint="latest").meta["update"] == 4
    _, raw = ckpt.read(run / "checkpoints" / "seed_1" / "update_0000004.msgpack")
    _assert_trees_equal(by_run.params, raw["params"])  # the checkpoint's network params, untouched
    seed_0 = jax.tree.leaves(pol.load(run, seed=0).params)
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(by_run.params), seed_0))  # seeds differ


def test_export_load_round_trip_gives_identical_actions(run, tmp_path):
    original = pol.load(run, seed=1)
    path = pol.export(tmp_path / "p.ocv2policy", params=original.params, model=original.model, env=original.env,
                      meta={"note": "round trip"})
    loaded = pol.load(path)
    _assert_trees_equal(original.params, loaded.params)
    assert (loaded.model, loaded.env, loaded.activation, loaded.hidden_size) == \
           (original.model, original.env, original.activation, original.hidden_size)
    assert loaded.meta == {"note": "round trip"}
    # The environment may also be given as the env object itself.
    by_env = pol.export(tmp_path / "e.ocv2policy", params=original.params, model=original.model,
                        env=original.make_env())
    assert pol.load(by_env).env == original.env
    for greedy in (False, True):
        np.testing.assert_array_equal(_act_trace(original, greedy=greedy), _act_trace(loaded, greedy=greedy))
    # The CLI writes the same policy (only the parameters, the network and the env: no training state).
    assert main(["export", str(run), "--seed", "1", "--out", str(tmp_path / "cli.ocv2policy")]) == 0
    via_cli = pol.load(tmp_path / "cli.ocv2policy")
    _assert_trees_equal(original.params, via_cli.params)
    np.testing.assert_array_equal(_act_trace(original), _act_trace(via_cli))
    header = json.loads(serialization.msgpack_restore((tmp_path / "cli.ocv2policy").read_bytes())["header"])
    assert header["format"] == pol.FORMAT_NAME and header["version"] == pol.FORMAT_VERSION
    assert set(header) == {"format", "version", "model", "activation", "env", "meta"}


def test_bad_sources_are_one_line_errors(run, tmp_path):
    garbage = tmp_path / "garbage.ocv2policy"
    garbage.write_bytes(b"\x00not msgpack at all")
    cases = {
        tmp_path / "missing": "no such file or directory",
        garbage: "not an ocv2 policy or checkpoint file",
        run / "checkpoints": "not a run directory",
    }
    for source, message in cases.items():
        with pytest.raises(pol.PolicyError, match=message) as error:
            pol.load(source)
        assert str(source) in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(pol.PolicyError, match="seeds 0..1, not seed 7"):
        pol.load(run, seed=7)
    with pytest.raises(pol.PolicyError, match="no checkpoint at update 3"):
        pol.load(run, checkpoint=3)
    with pytest.raises(pol.PolicyError, match="expected one of"):
        pol.load(run, checkpoint="best")
    with pytest.raises(pol.PolicyError, match="is one policy"):  # a file has no checkpoints to choose from
        pol.load(run / "checkpoints" / "seed_0" / "update_0000002.msgpack", checkpoint="mid")
    good = pol.load(run)
    future = tmp_path / "future.ocv2policy"
    pol.export(future, params=good.params, model=good.model, env=good.env)
    payload = serialization.msgpack_restore(future.read_bytes())
    payload["header"] = payload["header"].replace(f'"version": {pol.FORMAT_VERSION}', '"version": 99')
    future.write_bytes(serialization.msgpack_serialize(payload))
    with pytest.raises(pol.PolicyError, match="version 99"):
        pol.load(future)
    # Parameters that do not fit the network are refused before anything is written.
    wrong = tmp_path / "wrong.ocv2policy"
    with pytest.raises(pol.PolicyError, match="do not fit the network|parameter array"):
        pol.export(wrong, params=pol.load(run).params, model=good.model.__class__(kind="rnn"), env=good.env)
    assert not wrong.exists() and not list(tmp_path.glob(".wrong*"))
    # The CLI: a usage error (exit code 2) naming the file; nothing written.
    assert main(["export", str(garbage), "--out", str(tmp_path / "x.ocv2policy")]) == 2
    assert not (tmp_path / "x.ocv2policy").exists()


def test_ocv2_policy_is_population_policy_loaded_lazily():
    code = ("import sys, ocv2; assert 'population.policy' not in sys.modules and 'population' not in sys.modules; "
            "from ocv2 import policy; import population.policy as p; assert policy is p and ocv2.policy is p")
    subprocess.run([sys.executable, "-c", code], check=True)
