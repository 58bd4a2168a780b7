"""Actor-critic networks of the paper (appendix B): a feed-forward CNN and a 1x1-conv + CNN + GRU.

One calling convention for both, so PPO, evaluation and FCP never branch on the kind:

    hidden, logits, value = network.apply(params, hidden, obs, reset)

``obs`` is [T, B, H, W, C] (any integer or float dtype), ``reset`` bool[T, B] says "an episode starts
at this step" (the GRU carry is zeroed *before* reading that observation), ``hidden`` is [B, gru_dim]
(the CNN carries a [B, 0] placeholder). ``logits`` is [T, B, num_actions], ``value`` [T, B].
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax.linen.initializers import constant, orthogonal

from population.config import ModelConfig

_ACTIVATIONS = {"relu": nn.relu, "tanh": nn.tanh}


def _dense(features: int, scale: float) -> nn.Dense:
    return nn.Dense(features, kernel_init=orthogonal(scale), bias_init=constant(0.0))


class SameConv(nn.Module):
    """A stride-1, SAME-padded convolution computed as shifted slices + one matmul (im2col).

    Same function and parameters (``kernel`` [k, k, C, F], ``bias`` [F]) as ``nn.Conv``, but XLA:CPU
    runs its gradient about 4x faster than the convolution op on these small grids (see
    docs/BENCHMARKS.md); on GPU the matmul is just as good.
    """

    features: int
    kernel_size: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:  # [B, H, W, C] -> [B, H, W, F]
        k = self.kernel_size
        channels = x.shape[-1]
        kernel = self.param("kernel", orthogonal(math.sqrt(2)), (k, k, channels, self.features))
        bias = self.param("bias", constant(0.0), (self.features,))
        if k > 1:
            lo = (k - 1) // 2  # SAME padding puts the odd pixel after, as lax.conv does
            height, width = x.shape[1:3]
            padded = jnp.pad(x, ((0, 0), (lo, k - 1 - lo), (lo, k - 1 - lo), (0, 0)))
            x = jnp.concatenate([padded[:, i:i + height, j:j + width, :] for i in range(k) for j in range(k)], axis=-1)
        return x @ kernel.reshape(k * k * channels, self.features) + bias


class ConvEncoder(nn.Module):
    """Optional 1x1 per-cell mixer, then SAME-padded convs, flatten, Dense -> act -> LayerNorm."""

    mixer_features: Sequence[int]
    conv_features: Sequence[int]
    conv_kernels: Sequence[int]
    fc_dim: int
    activation: str

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:  # [B, H, W, C] -> [B, fc_dim]
        act = _ACTIVATIONS[self.activation]
        x = obs.astype(jnp.float32)
        for features in self.mixer_features:
            x = act(SameConv(features, 1)(x))
        for features, k in zip(self.conv_features, self.conv_kernels):
            x = act(SameConv(features, k)(x))
        x = x.reshape(x.shape[0], -1)
        x = act(_dense(self.fc_dim, math.sqrt(2))(x))
        return nn.LayerNorm()(x)


class ResetGRUCell(nn.Module):
    """A GRU step that zeroes its carry where an episode starts (flax default GRU initialisers)."""

    features: int

    @nn.compact
    def __call__(self, carry, inputs):
        x, reset = inputs
        carry = jnp.where(reset[:, None], jnp.zeros_like(carry), carry)
        return nn.GRUCell(self.features)(carry, x)


_ScannedGRU = nn.scan(ResetGRUCell, variable_broadcast="params", split_rngs={"params": False}, in_axes=0, out_axes=0)


class ActorCritic(nn.Module):
    """The paper's actor-critic. ``recurrent=False`` is the CNN (hidden passes through untouched)."""

    num_actions: int
    recurrent: bool
    mixer_features: Sequence[int]
    conv_features: Sequence[int]
    conv_kernels: Sequence[int]
    fc_dim: int
    gru_dim: int
    activation: str = "relu"

    @nn.compact
    def __call__(self, hidden: jax.Array, obs: jax.Array, reset: jax.Array):
        act = _ACTIVATIONS[self.activation]
        steps, batch = obs.shape[:2]
        flat = obs.reshape((steps * batch,) + obs.shape[2:])
        embedding = ConvEncoder(self.mixer_features, self.conv_features, self.conv_kernels, self.fc_dim,
                                self.activation)(flat).reshape(steps, batch, -1)
        if self.recurrent:
            hidden, embedding = _ScannedGRU(self.gru_dim)(hidden, (embedding, reset))
        actor = act(_dense(self.fc_dim, math.sqrt(2))(embedding))
        logits = _dense(self.num_actions, 0.01)(actor)
        critic = act(_dense(self.fc_dim, math.sqrt(2))(embedding))
        value = _dense(1, 1.0)(critic)[..., 0]
        return hidden, logits, value

    def initial_hidden(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.gru_dim if self.recurrent else 0), jnp.float32)


def make_network(model: ModelConfig, num_actions: int = 6, activation: str = "relu") -> ActorCritic:
    """The network a ``ModelConfig`` describes (the CNN has no 1x1 mixer)."""
    return ActorCritic(
        num_actions=num_actions,
        recurrent=model.recurrent,
        mixer_features=tuple(model.mixer_features) if model.recurrent else (),
        conv_features=tuple(model.conv_features),
        conv_kernels=tuple(model.conv_kernels),
        fc_dim=model.fc_dim,
        gru_dim=model.gru_dim,
        activation=activation,
    )


def init_params(network: ActorCritic, key: jax.Array, obs_shape: Sequence[int]):
    """Fresh parameters for observations of ``obs_shape`` (H, W, C); the key is consumed."""
    obs = jnp.zeros((1, 1) + tuple(obs_shape), jnp.float32)
    reset = jnp.zeros((1, 1), bool)
    return network.init(key, network.initial_hidden(1), obs, reset)


def count_params(params) -> int:
    return sum(int(x.size) for x in jax.tree.leaves(params))
