"""Observation and action spaces.

Spaces describe shapes and dtypes, sample random elements (for tests and env-only benchmarks) and check
membership. They are plain `eqx.Module`s with static sizes, so they can live inside an environment.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int, PRNGKeyArray, Shaped


def _dtype_and_shape(x) -> tuple[np.dtype, tuple[int, ...]]:
    """The dtype and shape of an array, a tracer or a Python value, read without computing anything."""
    if hasattr(x, "dtype") and hasattr(x, "shape"):
        return np.dtype(x.dtype), tuple(x.shape)
    a = np.asarray(x)
    return a.dtype, a.shape


class AbstractSpace(eqx.Module):
    """Base class of all spaces."""

    def sample(self, key: PRNGKeyArray) -> Array:
        raise NotImplementedError

    def as_action(self, action) -> Array:
        """`action` as the environment reads it; a ValueError (at trace time: from its dtype and shape alone) where
        it is not an element of this space's kind, so that it is never read as another action."""
        raise NotImplementedError

    def contains(self, x: Array) -> Bool[Array, ""]:
        raise NotImplementedError


class Discrete(AbstractSpace):
    """`n` actions, the integers `0 .. n-1`."""

    n: int = eqx.field(static=True)

    def __check_init__(self):
        if self.n < 1:
            raise ValueError(f"Discrete space needs n >= 1, got n={self.n}.")

    @property
    def shape(self) -> tuple[int, ...]:
        return ()

    @property
    def dtype(self):
        return jnp.int32

    def sample(self, key: PRNGKeyArray, mask: Bool[Array, " n"] | None = None) -> Int[Array, ""]:
        """A uniform random element; with `mask`, uniform over the allowed elements."""
        if mask is None:
            return jax.random.randint(key, (), 0, self.n, dtype=jnp.int32)
        logits = jnp.where(mask, 0.0, -jnp.inf)
        return jax.random.categorical(key, logits).astype(jnp.int32)

    def contains(self, x: Array) -> Bool[Array, ""]:
        return jnp.logical_and(x >= 0, x < self.n)

    def as_action(self, action) -> Int[Array, ""]:
        """An int32 scalar. A float, bool, string or batched action is refused: 0.5 would be read as action 0 and
        a shape-(1,) action would batch the state; an integer outside 0 … n-1 is the environment's to ignore."""
        dtype, shape = _dtype_and_shape(action)
        if shape != () or not np.issubdtype(dtype, np.integer):
            raise ValueError(f"Discrete({self.n}) actions are integer scalars (shape ()), got {dtype} of shape "
                             f"{shape}: pass one int per environment (jax.vmap the environment for a batch).")
        return jnp.asarray(action, jnp.int32)


class Box(AbstractSpace):
    """A box `[low, high]` of shape `shape` (bounds may be infinite)."""

    low: float = eqx.field(static=True)
    high: float = eqx.field(static=True)
    shape: tuple[int, ...] = eqx.field(static=True)
    dtype: type = eqx.field(static=True, default=jnp.float32)

    def sample(self, key: PRNGKeyArray) -> Shaped[Array, "..."]:
        if self.dtype in (bool, jnp.bool_):
            return jax.random.bernoulli(key, 0.5, self.shape)
        if jnp.issubdtype(self.dtype, jnp.integer):
            return jax.random.randint(key, self.shape, int(self.low), int(self.high) + 1).astype(self.dtype)
        lo = max(self.low, -1.0)
        hi = min(self.high, 1.0)
        return jax.random.uniform(key, self.shape, minval=lo, maxval=hi).astype(self.dtype)

    def contains(self, x: Array) -> Bool[Array, ""]:
        return jnp.logical_and(
            jnp.asarray(x.shape == self.shape), jnp.all((x >= self.low) & (x <= self.high))
        )

    def as_action(self, action) -> Shaped[Array, "..."]:
        """A real array of the space's shape and dtype (a bool, complex, string or wrongly shaped action is refused;
        bounds are the environment's to apply)."""
        dtype, shape = _dtype_and_shape(action)
        if shape != tuple(self.shape) or not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
            raise ValueError(f"Box actions of this environment are real arrays of shape {tuple(self.shape)}, got "
                             f"{dtype} of shape {shape} (jax.vmap the environment for a batch).")
        return jnp.asarray(action, self.dtype)


class DictSpace(AbstractSpace):
    """A dictionary of spaces, e.g. `{"obs": Box, "action_mask": Box}`."""

    spaces: dict = eqx.field(static=True)

    def sample(self, key: PRNGKeyArray) -> dict:
        keys = jax.random.split(key, len(self.spaces))
        return {k: s.sample(kk) for (k, s), kk in zip(self.spaces.items(), keys)}

    def contains(self, x: dict) -> Bool[Array, ""]:
        return jnp.all(jnp.stack([s.contains(x[k]) for k, s in self.spaces.items()]))

    def __getitem__(self, k: str) -> AbstractSpace:
        return self.spaces[k]
