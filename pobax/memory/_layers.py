"""Small layers shared by memories and agent heads: orthogonal-initialised dense layers and MLPs."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray


def expand_to(b: Array, ndim: int) -> Array:
    """A bias of shape (n,) as (1, ..., 1, n) with `ndim` axes: explicit broadcasting (rank promotion is an
    error in the tests, to catch (N, 1) − (N,) bugs)."""
    return jnp.reshape(b, (1,) * (ndim - 1) + b.shape)


class Dense(eqx.Module):
    """`y = W x + b`, W orthogonal with gain `scale`, b zero (the usual PPO initialisation)."""

    weight: Float[Array, "out in"]
    bias: Float[Array, " out"]

    def __init__(self, in_size: int, out_size: int, *, key: PRNGKeyArray, scale: float = math.sqrt(2.0)):
        self.weight = jax.nn.initializers.orthogonal(scale)(key, (out_size, in_size), jnp.float32)
        self.bias = jnp.zeros((out_size,), jnp.float32)

    def __call__(self, x: Float[Array, "*batch in"]) -> Float[Array, "*batch out"]:
        return x @ self.weight.T + expand_to(self.bias, x.ndim)


class MLP(eqx.Module):
    """Dense layers with ReLU between them (none after the last)."""

    layers: tuple[Dense, ...]

    def __init__(self, sizes: tuple[int, ...], *, key: PRNGKeyArray, final_scale: float = math.sqrt(2.0)):
        keys = jax.random.split(key, len(sizes) - 1)
        n = len(sizes) - 1
        self.layers = tuple(
            Dense(sizes[i], sizes[i + 1], key=keys[i], scale=final_scale if i == n - 1 else math.sqrt(2.0))
            for i in range(n)
        )

    def __call__(self, x: Float[Array, "*batch in"]) -> Float[Array, "*batch out"]:
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = jax.nn.relu(x)
        return x
