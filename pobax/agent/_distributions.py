"""Action distributions: categorical (with optional action mask) and diagonal Gaussian."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

# A large negative logit for masked actions: exp() underflows to exactly 0, and unlike -inf it never
# produces NaN in `0 * -inf` terms of the entropy.
_MASKED = -1e9


class Categorical(eqx.Module):
    """A categorical distribution over the last axis of `logits`; masked actions get probability 0."""

    logits: Float[Array, "*batch n"]

    @staticmethod
    def from_logits(logits: Float[Array, "*batch n"], mask: Bool[Array, "*batch n"] | None = None) -> "Categorical":
        if mask is not None:
            logits = jnp.where(mask, logits, _MASKED)
        return Categorical(jax.nn.log_softmax(logits, axis=-1))

    def sample(self, key: PRNGKeyArray) -> Int[Array, "*batch"]:
        return jax.random.categorical(key, self.logits, axis=-1).astype(jnp.int32)

    def mode(self) -> Int[Array, "*batch"]:
        return jnp.argmax(self.logits, axis=-1).astype(jnp.int32)

    def log_prob(self, action: Int[Array, "*batch"]) -> Float[Array, "*batch"]:
        return jnp.take_along_axis(self.logits, action[..., None].astype(jnp.int32), axis=-1)[..., 0]

    def entropy(self) -> Float[Array, "*batch"]:
        p = jnp.exp(self.logits)
        return -jnp.sum(p * self.logits, axis=-1)


class DiagGaussian(eqx.Module):
    """A Gaussian with diagonal covariance over the last axis."""

    mean: Float[Array, "*batch n"]
    log_std: Float[Array, "*batch n"]

    def sample(self, key: PRNGKeyArray) -> Float[Array, "*batch n"]:
        return self.mean + jnp.exp(self.log_std) * jax.random.normal(key, self.mean.shape)

    def mode(self) -> Float[Array, "*batch n"]:
        return self.mean

    def log_prob(self, action: Float[Array, "*batch n"]) -> Float[Array, "*batch"]:
        z = (action - self.mean) * jnp.exp(-self.log_std)
        return jnp.sum(-0.5 * z**2 - self.log_std - 0.5 * math.log(2 * math.pi), axis=-1)

    def entropy(self) -> Float[Array, "*batch"]:
        return jnp.sum(self.log_std + 0.5 * math.log(2 * math.pi * math.e), axis=-1)
