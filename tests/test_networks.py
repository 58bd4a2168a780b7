"""The paper's actor-critic networks (population/networks.py): sizes, initialisation, SameConv, GRU resets."""

from __future__ import annotations

import hashlib
import json

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ocv2
from population.config import ConfigError, ModelConfig, parse_config
from population.networks import (
    ActorCritic,
    SameConv,
    chunk_count,
    count_params,
    gru_scan,
    gru_sequence,
    gru_step,
    init_params,
    kernel_family,
    make_network,
    pointwise_mixer,
    same_function,
)
from population.numerics import matmul_precision, precision_in_force, relative_tolerance

RNN_OBS = (5, 5, 40)
SMALL_RNN = {
    "kind": "rnn",
    "mixer_features": [8],
    "conv_features": [4, 4],
    "conv_kernels": [3, 3],
    "fc_dim": 8,
    "gru_dim": 8,
}
SMALL_CNN = {"kind": "cnn", "conv_features": [4, 4], "conv_kernels": [3, 3], "fc_dim": 8}


def _model(raw: dict) -> ModelConfig:
    return parse_config({"model": raw}).model


def _dense(n_in: int, n_out: int) -> int:
    return n_in * n_out + n_out


def _conv(k: int, c_in: int, c_out: int) -> int:
    return k * k * c_in * c_out + c_out


def _init(network, key, obs_shape):
    """``init_params`` under one jit (much faster than op-by-op here; same values)."""
    return jax.jit(lambda k: init_params(network, k, obs_shape))(key)


def _shapes(params) -> dict:
    return {
        jax.tree_util.keystr(path): tuple(leaf.shape) for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]
    }


@pytest.fixture(scope="module")
def rnn():
    network = make_network(parse_config({}).model)
    return network, _init(network, jax.random.PRNGKey(0), RNN_OBS)


@pytest.fixture(scope="module")
def cnn():
    obs_shape = ocv2.make("cramped_room").obs_shape
    network = make_network(_model({"kind": "cnn"}))
    # shapes only: no values needed here
    return network, jax.eval_shape(lambda k: init_params(network, k, obs_shape), jax.random.PRNGKey(1)), obs_shape


# ---------------------------------------------------------------------------------------------------
# paper sizes
# ---------------------------------------------------------------------------------------------------


def test_rnn_paper_parameter_count_and_shapes(rnn):
    network, params = rnn
    h, w, c = RNN_OBS
    mixer = _conv(1, c, 128) + _conv(1, 128, 128) + _conv(1, 128, 8)
    convs = _conv(3, 8, 16) + _conv(3, 16, 32) + _conv(3, 32, 32)
    fc = _dense(h * w * 32, 128) + 2 * 128  # Dense 800 -> 128, LayerNorm scale + bias
    # flax GRUCell: input kernels ir/iz/in with biases, hidden kernels hr/hz without, hn with a bias
    gru = 3 * _dense(128, 128) + 3 * 128 * 128 + 128
    heads = _dense(128, 128) + _dense(128, 6) + _dense(128, 128) + _dense(128, 1)
    expected = mixer + convs + fc + gru + heads
    assert expected == 273_375
    assert count_params(params) == expected

    shapes = _shapes(params)
    enc = "['params']['ConvEncoder_0']"
    for i, kernel in enumerate(
        [(1, 1, 40, 128), (1, 1, 128, 128), (1, 1, 128, 8), (3, 3, 8, 16), (3, 3, 16, 32), (3, 3, 32, 32)]
    ):
        assert shapes[f"{enc}['SameConv_{i}']['kernel']"] == kernel
        assert shapes[f"{enc}['SameConv_{i}']['bias']"] == kernel[-1:]
    assert shapes[f"{enc}['Dense_0']['kernel']"] == (800, 128)
    assert shapes[f"{enc}['LayerNorm_0']['scale']"] == (128,)
    gru_prefix = "['params']['ScanResetGRUCell_0']['GRUCell_0']"
    gru_shapes = {k[len(gru_prefix) :]: v for k, v in shapes.items() if k.startswith(gru_prefix)}
    assert gru_shapes == {
        "['ir']['kernel']": (128, 128),
        "['ir']['bias']": (128,),
        "['iz']['kernel']": (128, 128),
        "['iz']['bias']": (128,),
        "['in']['kernel']": (128, 128),
        "['in']['bias']": (128,),
        "['hr']['kernel']": (128, 128),
        "['hz']['kernel']": (128, 128),
        "['hn']['kernel']": (128, 128),
        "['hn']['bias']": (128,),
    }
    heads_shapes = {
        name: shapes[f"['params']['{name}']['kernel']"] for name in ("Dense_0", "Dense_1", "Dense_2", "Dense_3")
    }
    assert heads_shapes == {"Dense_0": (128, 128), "Dense_1": (128, 6), "Dense_2": (128, 128), "Dense_3": (128, 1)}


def test_cnn_paper_parameter_count_and_shapes(cnn):
    network, params, (h, w, c) = cnn
    assert not network.recurrent and network.mixer_features == ()
    expected = (
        _conv(5, c, 32)
        + _conv(3, 32, 32)
        + _conv(3, 32, 32)
        + _dense(h * w * 32, 64)
        + 2 * 64
        + _dense(64, 64)
        + _dense(64, 6)
        + _dense(64, 64)
        + _dense(64, 1)
    )
    assert count_params(params) == expected
    shapes = _shapes(params)
    enc = "['params']['ConvEncoder_0']"
    assert shapes[f"{enc}['SameConv_0']['kernel']"] == (5, 5, c, 32)
    assert shapes[f"{enc}['SameConv_1']['kernel']"] == (3, 3, 32, 32)
    assert shapes[f"{enc}['SameConv_2']['kernel']"] == (3, 3, 32, 32)
    assert shapes[f"{enc}['Dense_0']['kernel']"] == (h * w * 32, 64)
    assert not any("GRU" in k for k in shapes)
    assert not any("SameConv_3" in k for k in shapes)


# ---------------------------------------------------------------------------------------------------
# initialisation
# ---------------------------------------------------------------------------------------------------


def _gram(kernel) -> np.ndarray:
    k = np.asarray(kernel, np.float64).reshape(-1, kernel.shape[-1])
    return k.T @ k


def test_initialisation_scales(rnn):
    _, params = rnn
    p = params["params"]
    policy = p["Dense_1"]["kernel"]
    assert policy.shape == (128, 6)
    np.testing.assert_allclose(_gram(policy), 0.01**2 * np.eye(6), atol=1e-9)
    np.testing.assert_allclose(_gram(p["Dense_3"]["kernel"]), np.eye(1), atol=1e-5)
    for name in ("Dense_0", "Dense_2"):
        np.testing.assert_allclose(_gram(p[name]["kernel"]), 2.0 * np.eye(128), atol=1e-4)
    enc = p["ConvEncoder_0"]
    np.testing.assert_allclose(_gram(enc["Dense_0"]["kernel"]), 2.0 * np.eye(128), atol=1e-4)
    # conv kernels: orthogonal sqrt(2) over the flattened (k*k*C, F) matrix (columns orthogonal when k*k*C >= F)
    for name in ("SameConv_1", "SameConv_3", "SameConv_5"):
        kernel = enc[name]["kernel"]
        np.testing.assert_allclose(_gram(kernel), 2.0 * np.eye(kernel.shape[-1]), atol=1e-4)
    for name in ("Dense_0", "Dense_1", "Dense_2", "Dense_3"):
        assert not np.any(np.asarray(p[name]["bias"]))
    for i in range(6):
        assert not np.any(np.asarray(enc[f"SameConv_{i}"]["bias"]))
    assert not np.any(np.asarray(enc["Dense_0"]["bias"]))
    np.testing.assert_array_equal(enc["LayerNorm_0"]["scale"], np.ones(128))
    # the policy really starts near uniform: logits are tiny compared to the value head's scale
    assert float(jnp.abs(policy).max()) < 0.01


# ---------------------------------------------------------------------------------------------------
# SameConv == nn.Conv(padding="SAME")
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kernel_size", [1, 3, 5, 4])
def test_same_conv_matches_flax_conv(kernel_size):
    x = jax.random.normal(jax.random.PRNGKey(kernel_size), (2, 5, 7, 3))
    module = SameConv(6, kernel_size)
    params = module.init(jax.random.PRNGKey(10 + kernel_size), x)
    assert params["params"]["kernel"].shape == (kernel_size, kernel_size, 3, 6)
    # a non-zero bias, so a dropped bias would be caught
    params = {"params": dict(params["params"], bias=jnp.arange(6, dtype=jnp.float32) * 0.1)}
    ours = module.apply(params, x)
    reference = nn.Conv(6, (kernel_size, kernel_size), padding="SAME").apply(params, x)
    assert ours.shape == reference.shape == (2, 5, 7, 6)
    tolerance = relative_tolerance()  # of the matmul precision in force: 1e-5 for float32 (a CPU's)
    np.testing.assert_allclose(ours, reference, atol=tolerance, rtol=tolerance)


# ---------------------------------------------------------------------------------------------------
# recurrence and the calling convention
# ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_rnn():
    obs_shape = (4, 5, 6)
    network = make_network(_model(SMALL_RNN))
    params = _init(network, jax.random.PRNGKey(2), obs_shape)
    # a sharper policy head so logits carry the GRU's state visibly
    params = jax.tree_util.tree_map_with_path(
        lambda path, x: x * 100.0 if "Dense_1" in jax.tree_util.keystr(path) else x, params
    )
    apply = jax.jit(network.apply)
    steps, batch = 6, 3
    obs = jax.random.randint(jax.random.PRNGKey(3), (steps, batch) + obs_shape, 0, 4).astype(jnp.uint8)
    hidden = jax.random.normal(jax.random.PRNGKey(4), (batch, network.gru_dim))
    return network, params, apply, obs, hidden


def test_gru_reset_starts_a_fresh_sequence(small_rnn):
    network, params, apply, obs, hidden = small_rnn
    steps, batch = obs.shape[:2]
    t = 3
    reset = jnp.zeros((steps, batch), bool).at[t].set(True)
    h_end, logits, value = apply(params, hidden, obs, reset)
    fresh_h, fresh_logits, fresh_value = apply(
        params, network.initial_hidden(batch), obs[t:], jnp.zeros((steps - t, batch), bool)
    )
    np.testing.assert_allclose(logits[t:], fresh_logits, atol=1e-6)
    np.testing.assert_allclose(value[t:], fresh_value, atol=1e-6)
    np.testing.assert_allclose(h_end, fresh_h, atol=1e-6)

    # without the reset the carry matters
    _, logits_nr, value_nr = apply(params, hidden, obs, jnp.zeros((steps, batch), bool))
    np.testing.assert_allclose(logits_nr[:t], logits[:t], atol=1e-6)  # before the reset: unchanged
    assert float(jnp.abs(logits_nr[t:] - fresh_logits).max()) > 1e-3
    assert float(jnp.abs(value_nr[t:] - fresh_value).max()) > 1e-4


def test_gru_reset_is_per_sequence_and_zeroes_before_reading(small_rnn):
    network, params, apply, obs, hidden = small_rnn
    steps, batch = obs.shape[:2]
    no_reset = jnp.zeros((steps, batch), bool)
    _, base_logits, _ = apply(params, hidden, obs, no_reset)
    # reset only sequence 0 at step 2: other sequences are untouched
    _, logits, _ = apply(params, hidden, obs, no_reset.at[2, 0].set(True))
    np.testing.assert_array_equal(logits[:, 1:], base_logits[:, 1:])
    assert float(jnp.abs(logits[2:, 0] - base_logits[2:, 0]).max()) > 1e-3
    # reset at step 0 == starting from a zero carry (the carry is zeroed before the first observation)
    _, reset0_logits, _ = apply(params, hidden, obs, no_reset.at[0].set(True))
    _, zero_logits, _ = apply(params, network.initial_hidden(batch), obs, no_reset)
    np.testing.assert_allclose(reset0_logits, zero_logits, atol=1e-6)


def test_output_shapes_and_cnn_placeholder_hidden():
    obs_shape = (4, 5, 6)
    steps, batch = 5, 3
    obs = jax.random.randint(jax.random.PRNGKey(5), (steps, batch) + obs_shape, 0, 4).astype(jnp.uint8)
    reset = jnp.zeros((steps, batch), bool)
    for raw in (SMALL_RNN, SMALL_CNN):
        network = make_network(_model(raw), num_actions=6)
        params = _init(network, jax.random.PRNGKey(6), obs_shape)
        apply = jax.jit(network.apply)
        hidden = network.initial_hidden(batch)
        expected_hidden = (batch, 8) if network.recurrent else (batch, 0)
        assert hidden.shape == expected_hidden
        new_hidden, logits, value = apply(params, hidden, obs, reset)
        assert new_hidden.shape == expected_hidden
        assert logits.shape == (steps, batch, 6)
        assert value.shape == (steps, batch)
        assert logits.dtype == value.dtype == jnp.float32
        if not network.recurrent:
            # the CNN is feed-forward: reset flags change nothing, each step depends on its own obs only
            _, logits_r, value_r = apply(params, hidden, obs, jnp.ones((steps, batch), bool))
            np.testing.assert_array_equal(logits_r, logits)
            np.testing.assert_array_equal(value_r, value)
            _, logits_rev, _ = apply(params, hidden, obs[::-1], reset)
            np.testing.assert_allclose(logits_rev[::-1], logits, atol=1e-6)


def test_make_network_follows_the_config():
    network = make_network(_model(SMALL_RNN), num_actions=4, activation="tanh")
    assert isinstance(network, ActorCritic)
    assert network.recurrent and network.num_actions == 4 and network.activation == "tanh"
    assert network.mixer_features == (8,) and network.conv_features == (4, 4) and network.gru_dim == 8
    params = jax.eval_shape(lambda k: init_params(network, k, (3, 3, 2)), jax.random.PRNGKey(7))
    assert params["params"]["Dense_1"]["kernel"].shape == (8, 4)
    assert params["params"]["ConvEncoder_0"]["SameConv_0"]["kernel"].shape == (1, 1, 2, 8)  # the 1x1 mixer
    assert params["params"]["ScanResetGRUCell_0"]["GRUCell_0"]["hn"]["kernel"].shape == (8, 8)


def test_the_chunked_mixer_equals_the_whole_mixer_values_and_gradients():
    """pointwise_mixer runs big inputs in cache-sized chunks (lax.map, recomputed in the backward
    pass); chunking must not change the function or its parameter gradients beyond float rounding."""
    key = jax.random.PRNGKey(0)
    shapes = [(6, 16), (16, 16), (16, 3)]
    weights = [
        (jax.random.normal(jax.random.fold_in(key, i), (1, 1) + s) * 0.5, jnp.full((s[1],), 0.1 * i))
        for i, s in enumerate(shapes)
    ]
    x = jax.random.randint(jax.random.PRNGKey(1), (12, 5, 5, 6), 0, 3).astype(jnp.uint8)  # 300 cells
    assert chunk_count(300, 64) == 5 and chunk_count(300, 0) == 1 and chunk_count(100, 64) == 1

    def loss(w, rows):
        return (pointwise_mixer(w, x, nn.relu, chunk_rows=rows) ** 2).sum()

    whole, chunked = pointwise_mixer(weights, x, nn.relu, 0), pointwise_mixer(weights, x, nn.relu, 64)
    assert chunked.shape == whole.shape == (12, 5, 5, 3) and float(jnp.abs(whole).max()) > 0
    np.testing.assert_allclose(chunked, whole, rtol=1e-6, atol=1e-6)
    tolerance = relative_tolerance()
    for ours, theirs in zip(jax.tree.leaves(jax.grad(loss)(weights, 64)), jax.tree.leaves(jax.grad(loss)(weights, 0))):
        np.testing.assert_allclose(ours, theirs, rtol=tolerance, atol=tolerance)


def test_the_gru_backward_pass_equals_autodiff_of_the_plain_scan():
    """gru_sequence has a hand-written backward pass (one kernel-gradient matmul after the loop);
    its gradients, through resets and both outputs, must equal autodiff of the plain step scan."""
    steps, batch, size = 12, 3, 5
    keys = jax.random.split(jax.random.PRNGKey(0), 7)
    projected = jax.random.normal(keys[0], (steps, batch, 3 * size))
    reset = jax.random.uniform(keys[1], (steps, batch)) < 0.25
    hidden = jax.random.normal(keys[2], (batch, size))
    kernel, bias = jax.random.normal(keys[3], (size, 3 * size)), jax.random.normal(keys[4], (size,))
    w_last, w_every = jax.random.normal(keys[5], (batch, size)), jax.random.normal(keys[6], (steps, batch, size))
    assert reset.any() and not reset.all()

    def plain(projected, reset, hidden, kernel, bias):
        def step(h, xs):
            return (h := gru_step(kernel, bias, h, *xs)[-1]), h

        return jax.lax.scan(step, hidden, (projected, reset))

    assert jax.tree.all(
        jax.tree.map(
            lambda x, y: bool((x == y).all()),
            gru_scan(projected, reset, hidden, kernel, bias),
            plain(projected, reset, hidden, kernel, bias),
        )
    )  # the "xla" kernels' GRU

    def loss(gru):
        def f(projected, hidden, kernel, bias):
            last, every = gru(projected, reset, hidden, kernel, bias)
            return (last * w_last).sum() + (every * w_every).sum()

        return jax.grad(f, argnums=(0, 1, 2, 3))

    np.testing.assert_array_equal(
        gru_sequence(projected, reset, hidden, kernel, bias)[1], plain(projected, reset, hidden, kernel, bias)[1]
    )
    for ours, theirs in zip(
        loss(gru_sequence)(projected, hidden, kernel, bias), loss(plain)(projected, hidden, kernel, bias), strict=True
    ):
        np.testing.assert_allclose(ours, theirs, rtol=relative_tolerance(), atol=relative_tolerance())


# ---------------------------------------------------------------------------------------------------
# kernel families: the CPU-tuned matmul forms on CPU, XLA's convolution and autodiff elsewhere
# ---------------------------------------------------------------------------------------------------


def _ops(network, params, obs, reset, hidden) -> str:
    """The network's jaxpr, as text: which primitives it runs (a custom_vjp call keeps its name here)."""
    return str(jax.make_jaxpr(network.apply)(params, hidden, obs, reset))


def test_the_kernel_family_follows_the_backend_unless_the_config_names_one(monkeypatch):
    assert kernel_family("auto") == "cpu"  # these tests run on CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert kernel_family("auto") == "xla" and kernel_family("cpu") == "cpu" and kernel_family("xla") == "xla"
    with pytest.raises(ValueError, match="model.kernels"):
        kernel_family("cudnn")
    network = make_network(_model(SMALL_RNN))  # kernels: auto, on a "GPU"
    obs, reset = jnp.zeros((2, 3, 4, 5, 6)), jnp.zeros((2, 3), bool)
    params = jax.eval_shape(lambda k: init_params(network, k, (4, 5, 6)), jax.random.PRNGKey(0))
    ops = _ops(network, params, obs, reset, network.initial_hidden(3))
    assert "conv_general_dilated" in ops and "custom_vjp" not in ops
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    ops = _ops(network, params, obs, reset, network.initial_hidden(3))
    assert "conv_general_dilated" not in ops and "custom_vjp" in ops
    forced = make_network(_model({**SMALL_RNN, "kernels": "xla"}))  # the config overrides the backend
    assert "conv_general_dilated" in _ops(forced, params, obs, reset, network.initial_hidden(3))


def test_model_kernels_is_validated_and_left_out_of_the_fingerprint_at_its_default(monkeypatch):
    assert parse_config({}).model.kernels == "auto"
    with pytest.raises(ConfigError, match="model.kernels: expected one of auto, cpu, xla, got 'gpu'"):
        parse_config({"model": {"kernels": "gpu"}})
    hashed = []  # what fingerprint hashes: runs made before the key existed keep their fingerprint
    real_sha256 = hashlib.sha256
    monkeypatch.setattr(hashlib, "sha256", lambda data=b"": hashed.append(json.loads(data)) or real_sha256(data))
    default = parse_config({}).fingerprint()
    assert "kernels" not in hashed[-1]["model"] and "gru_dim" in hashed[-1]["model"]
    assert parse_config({"model": {"kernels": "auto"}}).fingerprint() == default
    assert parse_config({"model": {"kernels": "xla"}}).fingerprint() != default
    assert "gru_backward" not in hashed[-1]["model"] and "gru_unroll" not in hashed[-1]["model"]
    assert parse_config({"model": {"gru_backward": "auto", "gru_unroll": 1}}).fingerprint() == default


# Ways to compute the same network: the two kernel families, each GRU backward pass in either, unrolled GRU loops
# (3 does not divide the 4 steps: the remainder runs outside the unrolled loop).
COMPUTATIONS = {
    "cpu": {"kernels": "cpu"},
    "xla": {"kernels": "xla"},
    "xla, hand-written GRU backward, unroll 4": {"kernels": "xla", "gru_backward": "hand", "gru_unroll": 4},
    "cpu, autodiff GRU, unroll 3": {"kernels": "cpu", "gru_backward": "autodiff", "gru_unroll": 3},
}


@pytest.mark.parametrize("raw, batch", [(SMALL_RNN, 3), (SMALL_RNN, 16), (SMALL_CNN, 3), (SMALL_CNN, 16)])
def test_every_kernel_family_gives_the_same_parameters_outputs_and_gradients(raw, batch):
    """A checkpoint trained with one family runs in the other: same parameter tree and initial values,
    same outputs and gradients to float rounding (batch 3 x 4 steps: SameConv's im2col form; 16 x 4:
    the banded form), whichever GRU backward pass and unrolling (``model.gru_backward``, ``gru_unroll``)."""
    obs_shape, steps = (4, 5, 6), 4
    obs = jax.random.randint(jax.random.PRNGKey(8), (steps, batch) + obs_shape, 0, 4).astype(jnp.uint8)
    reset = jax.random.uniform(jax.random.PRNGKey(9), (steps, batch)) < 0.3
    hidden = jax.random.normal(jax.random.PRNGKey(10), (batch, 8 if raw["kind"] == "rnn" else 0))
    results = {}
    for name, computation in COMPUTATIONS.items():
        network = make_network(_model({**raw, **computation}))
        params = _init(network, jax.random.PRNGKey(11), obs_shape)

        def loss(p):
            h, logits, value = network.apply(p, hidden, obs, reset)
            return (logits**2).sum() + (value**2).sum() + (h**2).sum(), (h, logits, value)

        results[name] = params, jax.jit(jax.grad(loss, has_aux=True))(params)
    cpu_params, (cpu_grads, cpu_out) = results["cpu"]
    assert float(jnp.abs(cpu_grads["params"]["ConvEncoder_0"]["SameConv_0"]["kernel"]).max()) > 0
    for name, (params, (grads, out)) in results.items():
        assert _shapes(cpu_params) == _shapes(params), name
        for ours, theirs in zip(jax.tree.leaves(cpu_params), jax.tree.leaves(params), strict=True):
            np.testing.assert_array_equal(ours, theirs)
        for ours, theirs in zip(jax.tree.leaves(cpu_out), jax.tree.leaves(out), strict=True):
            _assert_same_to_rounding(ours, theirs)
        for ours, theirs in zip(jax.tree.leaves(cpu_grads), jax.tree.leaves(grads), strict=True):
            _assert_same_to_rounding(ours, theirs)


def test_the_gru_backward_pass_and_unrolling_follow_the_config():
    obs, reset = jnp.zeros((4, 3, 4, 5, 6)), jnp.zeros((4, 3), bool)
    network = make_network(_model(SMALL_RNN))
    params = jax.eval_shape(lambda k: init_params(network, k, (4, 5, 6)), jax.random.PRNGKey(0))
    hidden = network.initial_hidden(3)

    def ops(**computation):
        return _ops(make_network(_model({**SMALL_RNN, **computation})), params, obs, reset, hidden)

    assert "custom_vjp" in ops(kernels="xla", gru_backward="hand")
    assert "custom_vjp" not in ops(kernels="cpu", gru_backward="autodiff")
    assert "unroll=4" in ops(gru_unroll=4) and "unroll=4" not in ops()
    with pytest.raises(ConfigError, match="model.gru_backward: expected one of auto, hand, autodiff"):
        parse_config({"model": {"gru_backward": "cudnn"}})
    with pytest.raises(ConfigError, match="model.gru_unroll: expected 1 to 64"):
        parse_config({"model": {"gru_unroll": 0}})


def _assert_same_to_rounding(ours, theirs):
    """Equal up to the rounding of sums whose order differs between two arrangements of the same matmuls,
    measured against the array's own scale: a gradient entry near 0 in a leaf whose entries reach 30 carries
    the rounding of those large terms (one such entry differed by 1.4e-5 on one CPU and not on another; the
    largest difference seen is 1.6e-6 of the leaf's largest entry). The rounding is that of the matmul
    precision in force (``population.numerics.relative_tolerance``: 1e-5 for float32, what a CPU always
    computes; 1e-3 for TF32, a GPU's default). A wrong kernel differs by the order of the values themselves."""
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    scale = float(np.abs(theirs).max()) if theirs.size else 0.0
    tolerance = relative_tolerance()
    np.testing.assert_allclose(ours, theirs, rtol=tolerance, atol=tolerance * max(scale, 1.0))


@pytest.mark.parametrize("precision, expected", [("float32", 1e-5), ("tf32", 1e-3), ("bf16", 1e-2)])
def test_the_tolerance_follows_the_matmul_precision(precision, expected):
    assert relative_tolerance(precision) == expected
    with matmul_precision(precision):
        in_force, tolerance = precision_in_force(), relative_tolerance()
    assert tolerance == relative_tolerance(in_force)
    if jax.default_backend() == "cpu" or precision == "float32":  # a CPU computes float32 whatever is asked
        assert in_force == "float32"


def test_configs_that_differ_only_in_kernels_describe_the_same_network():
    cpu, auto = _model({**SMALL_RNN, "kernels": "cpu"}), _model(SMALL_RNN)
    assert cpu != auto and same_function(cpu) == same_function(auto)
    assert same_function(cpu) != same_function(_model({**SMALL_RNN, "gru_dim": 4}))
    unrolled = _model({**SMALL_RNN, "gru_backward": "autodiff", "gru_unroll": 8})
    assert same_function(unrolled) == same_function(auto)
