"""Actor-critic networks of the paper (appendix B): a feed-forward CNN and a 1x1-conv + CNN + GRU.

One calling convention for both, so PPO, evaluation and FCP never branch on the kind:

    hidden, logits, value = network.apply(params, hidden, obs, reset)

``obs`` is [T, B, H, W, C] (any integer or float dtype), ``reset`` bool[T, B] says "an episode starts
at this step" (the GRU carry is zeroed *before* reading that observation), ``hidden`` is [B, gru_dim]
(the CNN carries a [B, 0] placeholder). ``logits`` is [T, B, num_actions], ``value`` [T, B].

Two kernel families compute the same function with the same parameter tree (``model.kernels``,
``kernel_family``): "cpu" builds convolutions from matmuls (``SameConv``) and gives the GRU a
hand-written backward pass (``gru_sequence``), both measured faster on XLA:CPU; "xla" uses
``nn.Conv`` and autodiff of the GRU scan, which is what GPUs (cuDNN) and other backends run best.
A checkpoint trained with either family loads and runs in the other.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax.linen.initializers import constant, orthogonal

from population.config import ModelConfig

# SameConv's banded path is used while W <= this x k: each output row's matmul spans all W cells of
# its k input rows, W / k times the multiply-adds im2col does, and up to about 3x that still costs
# less than im2col's shifted copies on XLA:CPU (measured on the grid sizes of the layouts).
BANDED_CELLS_PER_TAP = 3
# ... and while a call has at least this many samples: with fewer (acting in a few environments per
# policy under vmap, as SA collection and cross-play do), banded's H matmuls of `batch` rows each cost
# more than im2col's one matmul over batch*H*W rows.
BANDED_MIN_BATCH = 48
MIXER_CHUNK_ROWS = 2048  # cells per chunk of the 1x1 mixer (pointwise_mixer); 0: no chunking
CONV_PATH = "auto"  # or force "banded" / "im2col" everywhere (bench/train_throughput.py --conv-path)

_ACTIVATIONS = {"relu": nn.relu, "tanh": nn.tanh}
KERNEL_FAMILIES = ("cpu", "xla")
GRU_BACKWARDS = ("hand", "autodiff")


def kernel_family(kernels: str) -> str:
    """The kernel family ``model.kernels`` asks for: "cpu" or "xla"; "auto" picks "cpu" on the CPU
    backend (``jax.default_backend()``) and "xla" on any other (GPU, TPU)."""
    if kernels == "auto":
        return "cpu" if jax.default_backend() == "cpu" else "xla"
    if kernels not in KERNEL_FAMILIES:
        raise ValueError(f"model.kernels: expected auto, cpu or xla, got {kernels!r}")
    return kernels


def gru_backward_is_hand(gru_backward: str, family: str) -> bool:
    """Whether the GRU takes the hand-written backward pass (``gru_sequence``) rather than autodiff of its
    scan: ``model.gru_backward`` "hand" / "autodiff", or "auto": the hand-written one in the "cpu" family
    (measured faster on XLA:CPU), autodiff in the "xla" family."""
    if gru_backward == "auto":
        return family == "cpu"
    if gru_backward not in GRU_BACKWARDS:
        raise ValueError(f"model.gru_backward: expected auto, hand or autodiff, got {gru_backward!r}")
    return gru_backward == "hand"


def _dense(features: int, scale: float) -> nn.Dense:
    return nn.Dense(features, kernel_init=orthogonal(scale), bias_init=constant(0.0))


def row_shift_operator(width: int, kernel_size: int) -> np.ndarray:
    """0/1 float32[W, W, k]: entry [p, q, j] is 1 where input column p is kernel column j of output column q.

    SAME padding with the odd pixel after (as ``lax.conv``): columns outside the grid have no entry,
    so ``einsum("pqj,ijcf->ipcqf")`` with a kernel gives, for each kernel row i, the [W*C, W*F]
    matrix that maps one input grid row to its contribution to one output grid row.
    """
    lo = (kernel_size - 1) // 2
    op = np.zeros((width, width, kernel_size), np.float32)
    for q in range(width):
        for j in range(kernel_size):
            if 0 <= q + j - lo < width:
                op[q + j - lo, q, j] = 1.0
    return op


def conv_path(height: int, width: int, kernel_size: int, batch: int) -> str:
    """How ``SameConv`` computes a k x k convolution of ``batch`` samples on an H x W grid: "pointwise",
    "banded" or "im2col"."""
    if kernel_size == 1:
        return "pointwise"
    if CONV_PATH != "auto":
        return CONV_PATH
    banded = width <= BANDED_CELLS_PER_TAP * kernel_size and batch >= BANDED_MIN_BATCH
    return "banded" if banded else "im2col"


class SameConv(nn.Module):
    """A stride-1, SAME-padded convolution computed with matmuls, never XLA's convolution op.

    Same function and parameters (``kernel`` [k, k, C, F], ``bias`` [F]) as ``nn.Conv``. XLA:CPU runs
    the convolution op, and especially its gradient, slowly on these small grids (see
    docs/BENCHMARKS.md). Two exact formulations, picked by ``conv_path``:

    * banded: on grids at most ``BANDED_CELLS_PER_TAP`` x k cells wide (the egocentric 5x5 views
      always; for 3x3 kernels on full views, every layout up to 9 columns) and batches of at least
      ``BANDED_MIN_BATCH``, each output grid row is one matmul of the k input rows its kernel
      reaches (a contiguous [B, k*W*C] slice of the flattened activations) with a [k*W*C, W*F]
      matrix built from the kernel (``banded_rows``). It multiplies the zero padding along a row,
      but it makes no shifted copies of the activations, which is what makes im2col slow on these
      grids. It does not use one [H*W*C, H*W*F] matrix for the whole grid either: that would also
      multiply the zero blocks between rows more than k apart.
    * im2col: shifted slices concatenated along channels + one matmul, for wider grids and small batches.
    """

    features: int
    kernel_size: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:  # [B, H, W, C] -> [B, H, W, F]
        k = self.kernel_size
        batch, height, width, channels = x.shape
        kernel = self.param("kernel", orthogonal(math.sqrt(2)), (k, k, channels, self.features))
        bias = self.param("bias", constant(0.0), (self.features,))
        path = conv_path(height, width, k, batch)
        if path == "pointwise":  # 2-D, as pointwise_mixer (the networks' own 1x1 layers) does
            y = x.reshape(-1, channels) @ kernel.reshape(channels, self.features) + bias
            return y.reshape(batch, height, width, self.features)
        if path == "banded":
            shift = jnp.asarray(row_shift_operator(width, k))
            blocks = jnp.einsum("pqj,ijcf->ipcqf", shift, kernel).reshape(k, width * channels, width * self.features)
            y = banded_rows(x.reshape(batch, -1), blocks, height)
            return y.reshape(batch, height, width, self.features) + bias
        lo = (k - 1) // 2  # SAME padding puts the odd pixel after, as lax.conv does
        padded = jnp.pad(x, ((0, 0), (lo, k - 1 - lo), (lo, k - 1 - lo), (0, 0)))
        x = jnp.concatenate([padded[:, i : i + height, j : j + width, :] for i in range(k) for j in range(k)], axis=-1)
        return x @ kernel.reshape(k * k * channels, self.features) + bias


def banded_rows(rows: jax.Array, blocks: jax.Array, height: int) -> jax.Array:
    """A SAME convolution along grid rows: ``rows`` [B, H*W*C] (row-major grid), ``blocks`` [k, W*C, W*F]
    (kernel row i's matrix, ``row_shift_operator``) -> [B, H*W*F].

    Output row r is one matmul: input rows r - lo .. r - lo + k - 1 (those inside the grid: fewer at
    the edges) are a contiguous slice of ``rows``, times the matching kernel rows' blocks stacked.
    """
    taps, row_in, row_out = blocks.shape
    lo = (taps - 1) // 2  # SAME padding: lo rows above an output row, the rest below
    outputs = []
    for row in range(height):
        first, stop = max(0, lo - row), min(taps, height + lo - row)  # kernel rows inside the grid
        top = row - lo + first
        band = rows[:, top * row_in : (top + stop - first) * row_in]
        outputs.append(band @ blocks[first:stop].reshape(-1, row_out))
    return jnp.concatenate(outputs, axis=1)


class ConvEncoder(nn.Module):
    """Optional 1x1 per-cell mixer, then SAME-padded convs, flatten, Dense -> act -> LayerNorm."""

    mixer_features: Sequence[int]
    conv_features: Sequence[int]
    conv_kernels: Sequence[int]
    fc_dim: int
    activation: str
    kernels: str = "cpu"  # a kernel family ("cpu" or "xla"), already resolved

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:  # [B, H, W, C] -> [B, fc_dim]
        act = _ACTIVATIONS[self.activation]
        if self.kernels == "xla":
            x = self._xla_convs(obs.astype(jnp.float32), act)
        else:
            x = self._cpu_convs(obs, act)
        x = x.reshape(x.shape[0], -1)
        x = act(_dense(self.fc_dim, math.sqrt(2))(x))
        return nn.LayerNorm()(x)

    def _xla_convs(self, x: jax.Array, act) -> jax.Array:
        """``nn.Conv`` layers under SameConv's names (same parameters, same initial draws)."""
        kernels = (1,) * len(self.mixer_features) + tuple(self.conv_kernels)
        for index, (features, k) in enumerate(zip((*self.mixer_features, *self.conv_features), kernels)):
            x = act(
                nn.Conv(
                    features,
                    (k, k),
                    padding="SAME",
                    kernel_init=orthogonal(math.sqrt(2)),
                    bias_init=constant(0.0),
                    name=f"SameConv_{index}",
                )(x)
            )
        return x

    def _cpu_convs(self, obs: jax.Array, act) -> jax.Array:
        if self.mixer_features:
            channels, weights = obs.shape[-1], []
            for index, features in enumerate(self.mixer_features):
                weights.append(_ConvParams(features, 1, name=f"SameConv_{index}")(channels))
                channels = features
            x = pointwise_mixer(weights, obs, act)  # casts chunk by chunk: only the integer input is kept
        else:
            x = obs.astype(jnp.float32)
        for index, (features, k) in enumerate(zip(self.conv_features, self.conv_kernels)):
            x = act(SameConv(features, k, name=f"SameConv_{len(self.mixer_features) + index}")(x))
        return x


class _ConvParams(nn.Module):
    """Only the parameters of a ``SameConv`` (same names, shapes, initialisers and random draws)."""

    features: int
    kernel_size: int

    @nn.compact
    def __call__(self, channels: int):
        k = self.kernel_size
        kernel = self.param("kernel", orthogonal(math.sqrt(2)), (k, k, channels, self.features))
        return kernel, self.param("bias", constant(0.0), (self.features,))


def pointwise_mixer(weights, x: jax.Array, act, chunk_rows: int | None = None) -> jax.Array:
    """The 1x1 convs (``weights``: (kernel [1, 1, C, F], bias [F]) per layer) on every cell of ``x``.

    Computed as 2-D [cells, C] matmuls: a dot on the 4-D [B, H, W, C] array made XLA:CPU transpose
    the [cells, 128] activations for every weight gradient. Over a whole minibatch each layer's
    output is tens of MB, so the layers run on chunks of about ``chunk_rows`` cells (``lax.map``),
    back to back on data that stays in cache. Same numbers up to float summation order
    (tests/test_networks.py).
    """
    chunk_rows = MIXER_CHUNK_ROWS if chunk_rows is None else chunk_rows
    lead, channels = x.shape[:-1], x.shape[-1]
    rows = x.reshape(-1, channels)

    def layers(part):
        part = part.astype(jnp.float32)
        for kernel, bias in weights:
            part = act(part @ kernel.reshape(kernel.shape[-2], kernel.shape[-1]) + bias)
        return part

    chunks = chunk_count(rows.shape[0], chunk_rows)
    if chunks == 1:
        out = layers(rows)
    else:
        # checkpoint: the backward pass recomputes a chunk's layers from its (small, integer) input
        # instead of keeping every chunk's [rows, 128] activations, which costs more than the recompute
        out = jax.lax.map(jax.checkpoint(layers), rows.reshape(chunks, -1, channels)).reshape(rows.shape[0], -1)
    return out.reshape(lead + (out.shape[-1],))


def chunk_count(rows: int, chunk_rows: int) -> int:
    """The number of equal chunks closest to ``rows / chunk_rows`` that divides ``rows`` (1: no chunking)."""
    if chunk_rows <= 0 or rows < 2 * chunk_rows:
        return 1
    target = rows / chunk_rows
    return min((d for d in range(1, rows + 1) if rows % d == 0), key=lambda d: abs(d - target))


class _DenseParams(nn.Module):
    """Only the parameters of an ``nn.Dense`` (same names, shapes, initialisers and random draws)."""

    features: int
    use_bias: bool
    kernel_init: nn.initializers.Initializer

    @nn.compact
    def __call__(self, in_features: int):
        kernel = self.param("kernel", self.kernel_init, (in_features, self.features))
        bias = self.param("bias", constant(0.0), (self.features,)) if self.use_bias else None
        return kernel, bias


class _GRUParams(nn.Module):
    """The parameters of flax's ``nn.GRUCell``: input kernels ir/iz/in with biases, hidden hr/hz/hn (hn biased)."""

    features: int

    @nn.compact
    def __call__(self, in_features: int):
        dense_i = lambda name: _DenseParams(self.features, True, nn.initializers.lecun_normal(), name=name)
        dense_h = lambda name, bias=False: _DenseParams(self.features, bias, orthogonal(), name=name)
        # creation order = nn.GRUCell's, so the same init key draws the same values
        ir, hr = dense_i("ir")(in_features), dense_h("hr")(self.features)
        iz, hz = dense_i("iz")(in_features), dense_h("hz")(self.features)
        in_, hn = dense_i("in")(in_features), dense_h("hn", True)(self.features)
        input_kernel = jnp.concatenate([ir[0], iz[0], in_[0]], axis=1)  # [in, 3H]: gates r, z, n
        input_bias = jnp.concatenate([ir[1], iz[1], in_[1]])
        hidden_kernel = jnp.concatenate([hr[0], hz[0], hn[0]], axis=1)  # [H, 3H]
        return input_kernel, input_bias, hidden_kernel, hn[1]


class ResetGRU(nn.Module):
    """flax's ``nn.GRUCell`` over a sequence, zeroing the carry where an episode starts.

    Same function and parameter tree as ``nn.scan(GRUCell)`` (kept under the names that scan gave,
    so checkpoints stay loadable), computed faster: the input projections of all three gates for
    all T steps are one [T*B, in] x [in, 3H] matmul before the time loop, each step does one
    [B, H] x [H, 3H] matmul for the three hidden projections instead of three small ones, and the
    loop's backward pass is hand-written (``gru_sequence``; ``custom_backward=False``: autodiff of
    the same scan, ``gru_scan``). ``unroll`` steps run per loop iteration (``model.gru_unroll``).
    """

    features: int
    custom_backward: bool = True
    unroll: int = 1

    @nn.compact
    def __call__(self, hidden, inputs, reset):  # [B, H], [T, B, in], bool[T, B] -> ([B, H], [T, B, H])
        input_kernel, input_bias, hidden_kernel, hidden_bias = _GRUParams(self.features, name="GRUCell_0")(
            inputs.shape[-1]
        )
        flat = inputs.reshape(-1, inputs.shape[-1])  # 2-D: see pointwise_mixer on XLA:CPU and N-D dots
        projected = (flat @ input_kernel + input_bias).reshape(inputs.shape[:-1] + (-1,))  # [T, B, 3H]
        gru = gru_sequence if self.custom_backward else gru_scan
        return gru(projected, reset, hidden, hidden_kernel, hidden_bias, self.unroll)


def gru_step(hidden_kernel, hidden_bias, h, projected, start):
    """One GRU step: (h_prev after the reset, r, z, n, the n gate's hidden part, new h)."""
    size = h.shape[-1]
    h = jnp.where(start[:, None], jnp.zeros_like(h), h)
    hh = h @ hidden_kernel
    r = nn.sigmoid(projected[:, :size] + hh[:, :size])
    z = nn.sigmoid(projected[:, size : 2 * size] + hh[:, size : 2 * size])
    hidden_n = hh[:, 2 * size :] + hidden_bias
    n = jnp.tanh(projected[:, 2 * size :] + r * hidden_n)
    return h, r, z, n, hidden_n, (1.0 - z) * n + z * h


@functools.partial(jax.custom_vjp, nondiff_argnums=(5,))
def gru_sequence(projected, reset, hidden, hidden_kernel, hidden_bias, unroll=1):
    """The GRU over T steps: projected [T, B, 3H] input projections, reset bool[T, B], hidden [B, H]
    -> (last hidden [B, H], every hidden [T, B, H]); ``unroll`` steps per loop iteration, forward and
    backward (a GPU pays a fixed latency per iteration of a small loop body; the CPU hardly does).

    A hand-written backward pass (``jax.custom_vjp``): autodiff of the scan accumulated the hidden
    kernel's gradient with a small [H, B] x [B, 3H] matmul and a [H, 3H] add at every one of the T
    steps, sequentially. Here the backward loop only carries the hidden state's gradient and keeps
    each step's gate gradients; the kernel's gradient is then one [H, T*B] x [T*B, 3H] matmul.
    Same function; gradients equal autodiff's to float rounding (tests/test_networks.py).
    """
    return _gru_forward(projected, reset, hidden, hidden_kernel, hidden_bias, unroll)[0]  # unused gates: dropped by jit


def gru_scan(projected, reset, hidden, hidden_kernel, hidden_bias, unroll=1):
    """``gru_sequence`` differentiated by autodiff of the step scan (what backends other than XLA:CPU run)."""

    def step(h, xs):
        h = gru_step(hidden_kernel, hidden_bias, h, *xs)[-1]
        return h, h

    return jax.lax.scan(step, hidden, (projected, reset), unroll=unroll)


def _gru_forward(projected, reset, hidden, hidden_kernel, hidden_bias, unroll):
    def step(h, xs):
        h_prev, r, z, n, hidden_n, h = gru_step(hidden_kernel, hidden_bias, h, *xs)
        return h, (h, (h_prev, r, z, n, hidden_n))

    last, (every, gates) = jax.lax.scan(step, hidden, (projected, reset), unroll=unroll)
    return (last, every), (reset, hidden_kernel, gates)


def _gru_backward(unroll, residuals, cotangents):
    reset, hidden_kernel, gates = residuals
    d_last, d_every = cotangents
    size = d_last.shape[-1]
    hidden_kernel_t = hidden_kernel.T

    def step(dh, xs):
        d_out, start, (h_prev, r, z, n, hidden_n) = xs
        dh = dh + d_out
        d_pre_n = dh * (1.0 - z) * (1.0 - n * n)
        d_pre_r = d_pre_n * hidden_n * r * (1.0 - r)
        d_pre_z = dh * (h_prev - n) * z * (1.0 - z)
        d_hh = jnp.concatenate([d_pre_r, d_pre_z, d_pre_n * r], axis=-1)  # [B, 3H]
        d_prev = dh * z + d_hh @ hidden_kernel_t
        d_prev = jnp.where(start[:, None], jnp.zeros_like(d_prev), d_prev)
        return d_prev, (jnp.concatenate([d_pre_r, d_pre_z, d_pre_n], axis=-1), d_hh)

    d_hidden, (d_projected, d_hh) = jax.lax.scan(step, d_last, (d_every, reset, gates), reverse=True, unroll=unroll)
    h_prev = gates[0]
    d_kernel = h_prev.reshape(-1, size).T @ d_hh.reshape(-1, 3 * size)
    d_bias = d_hh[..., 2 * size :].sum(axis=(0, 1))
    return d_projected, None, d_hidden, d_kernel, d_bias


gru_sequence.defvjp(_gru_forward, _gru_backward)


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
    kernels: str = "auto"  # "auto", "cpu" or "xla": see kernel_family
    gru_backward: str = "auto"  # "auto" (the family's), "hand" or "autodiff": see gru_backward_is_hand
    gru_unroll: int = 1  # GRU time steps per loop iteration

    @nn.compact
    def __call__(self, hidden: jax.Array, obs: jax.Array, reset: jax.Array):
        act = _ACTIVATIONS[self.activation]
        family = kernel_family(self.kernels)
        steps, batch = obs.shape[:2]
        flat = obs.reshape((steps * batch,) + obs.shape[2:])
        embedding = ConvEncoder(
            self.mixer_features, self.conv_features, self.conv_kernels, self.fc_dim, self.activation, family
        )(flat).reshape(steps, batch, -1)
        if self.recurrent:
            hand = gru_backward_is_hand(self.gru_backward, family)
            gru = ResetGRU(self.gru_dim, hand, self.gru_unroll, name="ScanResetGRUCell_0")
            hidden, embedding = gru(hidden, embedding, reset)
        embedding = embedding.reshape(steps * batch, -1)  # 2-D heads: see pointwise_mixer
        actor = act(_dense(self.fc_dim, math.sqrt(2))(embedding))
        logits = _dense(self.num_actions, 0.01)(actor).reshape(steps, batch, -1)
        critic = act(_dense(self.fc_dim, math.sqrt(2))(embedding))
        value = _dense(1, 1.0)(critic).reshape(steps, batch)
        return hidden, logits, value

    def initial_hidden(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.gru_dim if self.recurrent else 0), jnp.float32)


def same_function(model: ModelConfig) -> ModelConfig:
    """``model`` with the kernel choice reset: two configs equal after this describe the same network
    (parameters and function), however its kernels compute it (family, GRU backward pass, unrolling)."""
    return dataclasses.replace(model, kernels="auto", gru_backward="auto", gru_unroll=1)


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
        kernels=model.kernels,
        gru_backward=model.gru_backward,
        gru_unroll=model.gru_unroll,
    )


def init_params(network: ActorCritic, key: jax.Array, obs_shape: Sequence[int]):
    """Fresh parameters for observations of ``obs_shape`` (H, W, C); the key is consumed."""
    obs = jnp.zeros((1, 1) + tuple(obs_shape), jnp.float32)
    reset = jnp.zeros((1, 1), bool)
    return network.init(key, network.initial_hidden(1), obs, reset)


def count_params(params) -> int:
    return sum(int(x.size) for x in jax.tree.leaves(params))
