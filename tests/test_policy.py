"""population.policy and ``ocv2 export``: loading every kind of source, the export/load
round trip, acting, and one-line errors for bad input."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization
from policy_runs import shared_run

from cluster.cli import main
from population import checkpoints as ckpt
from population import policy as pol
from population import sealed
from population.config import load_run_config


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
    # the training config it came from, which an exported file keeps (below)
    assert by_run.meta["fingerprint"] == load_run_config(run).fingerprint()
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
    path = pol.export(
        tmp_path / "p.ocv2policy",
        params=original.params,
        model=original.model,
        env=original.env,
        meta={"note": "round trip"},
    )
    loaded = pol.load(path)
    _assert_trees_equal(original.params, loaded.params)
    assert (loaded.model, loaded.env, loaded.activation, loaded.hidden_size) == (
        original.model,
        original.env,
        original.activation,
        original.hidden_size,
    )
    assert loaded.meta == {"note": "round trip"}
    # The environment may also be given as the env object itself.
    by_env = pol.export(
        tmp_path / "e.ocv2policy", params=original.params, model=original.model, env=original.make_env()
    )
    assert pol.load(by_env).env == original.env
    for greedy in (False, True):
        np.testing.assert_array_equal(_act_trace(original, greedy=greedy), _act_trace(loaded, greedy=greedy))
    # The CLI writes the same policy (only the parameters, the network and the env: no training state).
    assert main(["export", str(run), "--seed", "1", "--out", str(tmp_path / "cli.ocv2policy")]) == 0
    via_cli = pol.load(tmp_path / "cli.ocv2policy")
    _assert_trees_equal(original.params, via_cli.params)
    np.testing.assert_array_equal(_act_trace(original), _act_trace(via_cli))
    content = _content(tmp_path / "cli.ocv2policy")
    header = json.loads(content["header"])
    assert header["format"] == pol.FORMAT_NAME and header["version"] == pol.FORMAT_VERSION
    assert set(header) == {"format", "version", "model", "activation", "env", "meta"}
    assert header["meta"]["fingerprint"] == load_run_config(run).fingerprint()  # the config it was trained with


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
    with pytest.raises(pol.PolicyError, match="expected one of"):  # a digit to str.isdigit, not to int
        pol.load(run, checkpoint="\u00b2")
    with pytest.raises(pol.PolicyError, match="is one policy"):  # a file has no checkpoints to choose from
        pol.load(run / "checkpoints" / "seed_0" / "update_0000002.msgpack", checkpoint="mid")
    good = pol.load(run)
    future = tmp_path / "future.ocv2policy"
    pol.export(future, params=good.params, model=good.model, env=good.env)
    cut = tmp_path / "cut.ocv2policy"
    cut.write_bytes(future.read_bytes()[:1000])  # a copy that stopped part-way
    with pytest.raises(pol.PolicyError, match="a damaged or cut one .msgpack: .*incomplete"):
        pol.load(cut)
    future.write_bytes(sealed.seal(pol.FORMAT_NAME, 99, _content(future)))
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


@pytest.mark.parametrize("seed", ["1", True, 1.5])
def test_a_seed_that_is_not_an_int_is_a_one_line_error(run, seed):
    for source in (run, run / "checkpoints" / "seed_1"):
        with pytest.raises(pol.PolicyError, match=f"seed {seed!r} must be an int, not a {type(seed).__name__}"):
            pol.load(source, seed=seed)
    assert pol.load(run, seed=np.int64(1)).meta["seed"] == 1  # any integer type is a seed


@pytest.mark.parametrize("source", [None, b"run", 3])
def test_a_source_that_is_not_a_path_is_a_one_line_error(source):
    with pytest.raises(pol.PolicyError, match=f"source must be a path .*, got {type(source).__name__}$"):
        pol.load(source)


def test_the_environment_package_does_not_alias_the_policy_api():
    """``ocv2.policy`` was an alias reaching up into population/; it is gone, and its error says where to look."""
    import ocv2

    with pytest.raises(AttributeError, match="from population import policy"):
        ocv2.policy  # noqa: B018
    with pytest.raises(ImportError):
        from ocv2 import policy  # noqa: F401


def _content(path):
    """The header and parameters inside an exported file (its checksum checked)."""
    return sealed.unseal(serialization.msgpack_restore(path.read_bytes()), pol.FORMAT_NAME, pol.FORMAT_VERSION)


@pytest.fixture(scope="module")
def exported(run, tmp_path_factory):
    policy = pol.load(run)
    path = pol.export(
        tmp_path_factory.mktemp("exported") / "p.ocv2policy",
        params=policy.params,
        model=policy.model,
        env=policy.env,
        meta={"note": "checked"},
    )
    return policy, path


def test_any_flipped_byte_of_an_export_is_refused(exported, tmp_path):
    policy, path = exported
    data = path.read_bytes()
    body_start = data.index(_content(path)["header"].encode()[:16]) - 64  # frame, body header, header text
    rng = np.random.default_rng(0)
    offsets = [*range(min(len(data), body_start + 400)), *rng.integers(0, len(data), 300), len(data) - 1]
    damaged = tmp_path / "damaged.ocv2policy"
    for offset in offsets:
        damaged.write_bytes(data[:offset] + bytes([data[offset] ^ 1 << int(offset) % 8]) + data[offset + 1 :])
        with pytest.raises(pol.PolicyError) as error:
            pol.load(damaged)
        assert str(damaged) in str(error.value) and "\n" not in str(error.value), offset


def _reseal(path, out, edit):
    content = _content(path)
    edit(content)
    out.write_bytes(sealed.seal(pol.FORMAT_NAME, pol.FORMAT_VERSION, content))
    return out


@pytest.mark.parametrize(
    "value, message",
    [
        (np.nan, "holds NaN or infinite values"),
        (np.inf, "holds NaN or infinite values"),
        (1 + 2j, "dtype complex64, not a floating-point one"),
        (1, "dtype int32, not a floating-point one"),
    ],
)
def test_non_finite_or_non_float_parameters_are_refused(exported, tmp_path, value, message):
    policy, path = exported
    leaves, treedef = jax.tree.flatten(jax.tree.map(np.asarray, policy.params))
    first = leaves[0]
    dtype = np.complex64 if isinstance(value, complex) else np.int32 if isinstance(value, int) else first.dtype
    bad = first.astype(dtype)
    bad.flat[0] = value
    params = jax.tree.unflatten(treedef, [bad, *leaves[1:]])
    target = tmp_path / "bad.ocv2policy"
    with pytest.raises(pol.PolicyError, match=message):  # export refuses them before writing ...
        pol.export(target, params=params, model=policy.model, env=policy.env)
    assert not target.exists()

    def plant(content):  # ... and a file that carries them (with a valid checksum) is refused on load
        content["params"] = serialization.to_state_dict(params)

    with pytest.raises(pol.PolicyError, match=message) as error:
        pol.load(_reseal(path, target, plant))
    assert str(target) in str(error.value)


def test_a_version_1_export_loads_with_a_warning(exported, tmp_path):
    policy, path = exported
    content = _content(path)
    header = json.loads(content["header"])
    header["version"] = 1
    old = tmp_path / "old.ocv2policy"
    old.write_bytes(serialization.msgpack_serialize({"header": json.dumps(header), "params": content["params"]}))
    with pytest.warns(pol.PolicyFormatWarning, match="version-1 file has no checksum"):
        loaded = pol.load(old)
    _assert_trees_equal(loaded.params, policy.params)
    np.testing.assert_array_equal(_act_trace(loaded), _act_trace(policy))


def test_a_header_nested_100000_deep_is_a_one_line_error(exported, tmp_path, capsys):
    _, path = exported
    deep = "[" * 100_000 + "]" * 100_000
    sealed_file = _reseal(path, tmp_path / "deep.ocv2policy", lambda content: content.update(header=deep))
    old_file = tmp_path / "deep_v1.ocv2policy"
    old_file.write_bytes(serialization.msgpack_serialize({"header": deep, "params": _content(path)["params"]}))
    for source in (sealed_file, old_file):
        with pytest.raises(pol.PolicyError, match="nested deeper than 32 levels"):
            pol.load(source)
        assert main(["xp", "--rows", str(source), "--backend", "local", "--out", str(tmp_path / "xp")]) == 2
        err = capsys.readouterr().err
        assert "nested deeper than 32 levels" in err and str(source) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "xp").exists()
