"""A change detector: the PPO trainer's numbers are those of the implementation it was optimised from.

These tests do not show that PPO is correct or learns (tests/test_ppo.py checks its parts against hand
computations, tests/test_learning.py that it learns); they show that an optimisation changed nothing but
floating-point summation order. A deliberate change of the numbers (a new initialiser, another loss
term) fails them by design: re-record the expected values then, and say why in the commit.

The hot path (population/networks.py, population/ppo.py) was rewritten for speed: dense SameConv
matrices on small grids, the GRU's input projection as one matmul outside the time loop, and so on.
These tests train two updates of a small RNN (1x1 mixer + 3x3 convs + GRU, 5x5 view) and a small CNN
(5x5 and 3x3 convs, full Cramped Room view) and compare the losses and trained parameters with the
values the previous straightforward implementation (im2col convolutions, flax's scanned GRUCell)
produced for the same config and seed. Only floating-point summation order may differ.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from population import ppo
from population.config import parse_config
from population.networks import SameConv, conv_path

_PPO = {
    "num_envs": 4,
    "num_steps": 16,
    "num_minibatches": 2,
    "update_epochs": 2,
    "total_timesteps": 512,
    "rew_shaping_horizon": 256,
}
CONFIGS = {
    "rnn": {
        "env": {"layout": "grounded_coord_simple", "agent_view_size": 2, "max_steps": 20, "negative_rewards": True},
        "model": {
            "kind": "rnn",
            "mixer_features": [8, 4],
            "conv_features": [4, 4],
            "conv_kernels": [3, 3],
            "fc_dim": 8,
            "gru_dim": 8,
        },
        "ppo": _PPO,
    },
    "cnn": {
        "env": {"layout": "cramped_room", "max_steps": 20},
        "model": {"kind": "cnn", "conv_features": [4, 4], "conv_kernels": [5, 3], "fc_dim": 8},
        "ppo": _PPO,
    },
}

# Recorded from the previous implementation: per-update mean losses of updates 1 and 2, and per
# parameter leaf (sum, sum of |x|, sum of x * cos(index)) after both updates.
REFERENCE = {
    "rnn": {
        "loss": {
            "total": [-0.0112253204, 0.0135953482],
            "actor": [-7.04801641e-05, -6.42091036e-05],
            "value": [0.0135253593, 0.0631541312],
            "entropy": [1.79175198, 1.79175115],
        },
        "params": {
            "ConvEncoder_0/Dense_0/bias": (-0.00181667542, 0.00652745087, -0.001519983),
            "ConvEncoder_0/Dense_0/kernel": (-3.21531034, 91.7614288, -3.13694199),
            "ConvEncoder_0/LayerNorm_0/bias": (-0.00260008126, 0.00688956492, -0.00117431763),
            "ConvEncoder_0/LayerNorm_0/scale": (7.99908352, 7.99908352, 1.47683646),
            "ConvEncoder_0/SameConv_0/bias": (0.0017558235, 0.0062984135, -0.000752218084),
            "ConvEncoder_0/SameConv_0/kernel": (1.08451176, 57.6155167, 4.82773213),
            "ConvEncoder_0/SameConv_1/bias": (0.0025063341, 0.00286975014, 0.00216067581),
            "ConvEncoder_0/SameConv_1/kernel": (-1.5827384, 11.6683159, 1.14311753),
            "ConvEncoder_0/SameConv_2/bias": (0.00234221341, 0.00246676011, 0.000344099461),
            "ConvEncoder_0/SameConv_2/kernel": (3.92297196, 26.6726494, 0.524394629),
            "ConvEncoder_0/SameConv_3/bias": (0.00161358865, 0.00251655607, 0.00201813351),
            "ConvEncoder_0/SameConv_3/kernel": (4.99843025, 28.1686554, 0.265773242),
            "Dense_0/bias": (-0.00146083673, 0.00630758144, -0.00145577008),
            "Dense_0/kernel": (0.253603935, 26.5489311, -2.06192816),
            "Dense_1/bias": (-0.000333146541, 0.00539940037, 0.00351109248),
            "Dense_1/kernel": (-0.0612249859, 0.142995045, 0.00731675873),
            "Dense_2/bias": (-0.000399673707, 0.00733010564, -0.00333094241),
            "Dense_2/kernel": (1.52626133, 26.1180286, -0.2434944),
            "Dense_3/bias": (0.000969258545, 0.000969258545, 0.000969258545),
            "Dense_3/kernel": (-0.212605, 2.30272007, -0.915657018),
            "ScanResetGRUCell_0/GRUCell_0/hn/bias": (0.00389555469, 0.00611272268, 0.00036185333),
            "ScanResetGRUCell_0/GRUCell_0/hn/kernel": (0.81957233, 18.0405254, 0.713114155),
            "ScanResetGRUCell_0/GRUCell_0/hr/kernel": (2.57460356, 18.6097527, -2.20198794),
            "ScanResetGRUCell_0/GRUCell_0/hz/kernel": (2.42627954, 18.731905, 2.26213361),
            "ScanResetGRUCell_0/GRUCell_0/in/bias": (0.0036583622, 0.00716467109, -0.000154375814),
            "ScanResetGRUCell_0/GRUCell_0/in/kernel": (2.85312891, 15.2118139, 2.05971006),
            "ScanResetGRUCell_0/GRUCell_0/ir/bias": (0.00147135463, 0.00562200462, 0.00163797746),
            "ScanResetGRUCell_0/GRUCell_0/ir/kernel": (2.79610372, 19.461977, 0.566954714),
            "ScanResetGRUCell_0/GRUCell_0/iz/bias": (-0.00289355172, 0.00848221313, -0.000968869563),
            "ScanResetGRUCell_0/GRUCell_0/iz/kernel": (-6.49252224, 21.0334473, -0.440430642),
        },
    },
    "cnn": {
        "loss": {
            "total": [0.10864152, 0.185650647],
            "actor": [-0.000124665676, -9.52160917e-06],
            "value": [0.253366888, 0.407154918],
            "entropy": [1.79172587, 1.79172885],
        },
        "params": {
            "ConvEncoder_0/Dense_0/bias": (0.00135709508, 0.00821683276, 7.99268738e-05),
            "ConvEncoder_0/Dense_0/kernel": (-3.16753507, 82.220047, -3.20357678),
            "ConvEncoder_0/LayerNorm_0/bias": (-0.00194487302, 0.0110027436, -0.000630982726),
            "ConvEncoder_0/LayerNorm_0/scale": (7.99504995, 7.99504995, 1.47340363),
            "ConvEncoder_0/SameConv_0/bias": (0.00206315145, 0.00209034793, 0.00140167723),
            "ConvEncoder_0/SameConv_0/kernel": (-1.03543413, 122.650826, 4.32145504),
            "ConvEncoder_0/SameConv_1/bias": (0.00170213915, 0.00436696038, 0.00186767176),
            "ConvEncoder_0/SameConv_1/kernel": (0.0117563009, 26.8593979, -1.69415567),
            "Dense_0/bias": (-0.00206435611, 0.00360868592, -0.00103374866),
            "Dense_0/kernel": (0.259123564, 26.5520153, -2.05511085),
            "Dense_1/bias": (0.000601776061, 0.00354915624, -0.00185291392),
            "Dense_1/kernel": (-0.0460045375, 0.13878496, -0.00278889333),
            "Dense_2/bias": (-0.00195425563, 0.00737426989, 0.00212257408),
            "Dense_2/kernel": (1.53814173, 26.1157494, -0.254298213),
            "Dense_3/bias": (0.000337333651, 0.000337333651, 0.000337333651),
            "Dense_3/kernel": (-0.217475176, 2.30035305, -0.913928664),
        },
    },
}


def _fingerprint(x) -> tuple[float, float, float]:
    x = np.asarray(x, np.float64).ravel()
    return float(x.sum()), float(np.abs(x).sum()), float((x * np.cos(np.arange(x.size))).sum())


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_two_updates_match_the_reference_implementation(name):
    trainer = ppo.make_trainer(parse_config(CONFIGS[name]))
    # the key the reference run's seed 0 had, spelled out so a change of key derivation cannot move it
    key = jax.random.fold_in(jax.random.PRNGKey(0), 0)
    state = jax.jit(lambda k: ppo.init_train_state(trainer, k))(key)
    state, metrics = jax.jit(lambda s: ppo.advance(trainer, s, 2))(state)
    reference = REFERENCE[name]
    for field, expected in reference["loss"].items():
        np.testing.assert_allclose(
            np.asarray(getattr(metrics.loss, field)), expected, rtol=1e-4, atol=1e-6, err_msg=f"{name} loss {field}"
        )
    leaves = {
        "/".join(str(k.key) for k in path[1:]): x for path, x in jax.tree_util.tree_leaves_with_path(state.params)
    }
    assert sorted(leaves) == sorted(reference["params"])  # same parameter tree: checkpoints stay loadable
    for key, expected in reference["params"].items():
        np.testing.assert_allclose(_fingerprint(leaves[key]), expected, rtol=1e-4, atol=2e-5, err_msg=f"{name} {key}")


@pytest.mark.parametrize(
    "batch, shape, kernel_size, path",
    [
        (48, (5, 5), 3, "banded"),
        (48, (4, 5), 5, "banded"),
        (48, (9, 9), 3, "banded"),
        (48, (2, 7), 5, "banded"),
        (48, (5, 6), 4, "banded"),
        (47, (5, 5), 3, "im2col"),
        (48, (4, 15), 3, "im2col"),
        (48, (6, 11), 3, "im2col"),
        (3, (5, 7), 1, "pointwise"),
    ],
)
def test_same_conv_paths_match_flax_conv(batch, shape, kernel_size, path):
    assert conv_path(*shape, kernel_size, batch) == path
    x = jax.random.normal(jax.random.PRNGKey(1), (batch,) + shape + (4,))
    module = SameConv(5, kernel_size)
    params = module.init(jax.random.PRNGKey(2), x)
    params = {"params": dict(params["params"], bias=jnp.arange(5, dtype=jnp.float32) * 0.1)}
    reference = nn.Conv(5, (kernel_size, kernel_size), padding="SAME").apply(params, x)
    np.testing.assert_allclose(module.apply(params, x), reference, atol=1e-5, rtol=1e-5)
    grads = jax.grad(lambda p: (module.apply(p, x) ** 2).sum())(params)
    ref_grads = jax.grad(lambda p: (nn.Conv(5, (kernel_size, kernel_size), padding="SAME").apply(p, x) ** 2).sum())(
        params
    )
    # The gradients sum batch x height x width products in an order that differs between the two convolutions
    # and between XLA versions, so an entry near 0 in a leaf whose entries reach thousands carries the float32
    # rounding of those large terms: compare at each leaf's own scale. The largest difference seen is 7.9e-7
    # of the leaf's largest entry, about 7 float32 ulps (2^-23 = 1.2e-7 relative) at that scale (jax 0.12.0.1
    # on CPU: 1.7e-4 in a kernel gradient whose entries reach 2.3e3; 4.2e-7 with jax 0.10.2). The tolerance,
    # 1e-5 of the largest entry, leaves 10x room; a wrong path differs by the order of the values themselves.
    for ours, theirs in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads), strict=True):
        scale = float(np.abs(np.asarray(theirs)).max())
        np.testing.assert_allclose(ours, theirs, atol=1e-5 * max(scale, 1.0), rtol=1e-4)
