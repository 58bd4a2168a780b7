"""Minimal action/observation spaces with the true dtype and bounds (no gym dependency)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class Discrete:
    """Integers 0 .. n-1."""

    n: int
    dtype: jnp.dtype = jnp.int32
    shape: tuple = ()

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, self.shape, 0, self.n, dtype=self.dtype)

    def contains(self, x) -> bool:
        x = jnp.asarray(x)
        return bool(
            jnp.issubdtype(x.dtype, jnp.integer) and x.shape == self.shape and (x >= 0).all() and (x < self.n).all()
        )


@dataclasses.dataclass(frozen=True)
class Box:
    """Arrays of ``shape``/``dtype`` with every value in [low, high]."""

    low: float
    high: float
    shape: tuple
    dtype: jnp.dtype

    def sample(self, key: jax.Array) -> jax.Array:
        if jnp.issubdtype(self.dtype, jnp.integer):
            return jax.random.randint(key, self.shape, int(self.low), int(self.high) + 1).astype(self.dtype)
        return jax.random.uniform(key, self.shape, self.dtype, self.low, self.high)

    def contains(self, x) -> bool:
        x = jnp.asarray(x)
        return bool(
            x.shape == tuple(self.shape) and x.dtype == self.dtype and (x >= self.low).all() and (x <= self.high).all()
        )
