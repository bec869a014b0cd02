"""Generalised advantage estimation that separates termination from truncation.

For a step t with value `v_t`, reward `r_t` and `next_value_t` — the value of the observation that followed
step t *within the same episode* (for a truncated episode, the value of its final observation) —

    δ_t = r_t + γ (1 − terminated_t) next_value_t − v_t
    A_t = δ_t + γ λ (1 − done_t) A_{t+1},       done_t = terminated_t or truncated_t

A terminated episode does not bootstrap; a truncated one bootstraps from its final observation; neither lets
the advantage leak into the next episode.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


def gae(
    rewards: Float[Array, "time *batch"],
    values: Float[Array, "time *batch"],
    next_values: Float[Array, "time *batch"],
    terminated: Bool[Array, "time *batch"],
    truncated: Bool[Array, "time *batch"],
    gamma: Float[Array, ""] | float,
    lam: Float[Array, ""] | float,
) -> tuple[Float[Array, "time *batch"], Float[Array, "time *batch"]]:
    """Advantages and value targets (`advantages + values`), scanning backwards over time."""
    not_term = 1.0 - terminated.astype(values.dtype)
    not_done = 1.0 - jnp.logical_or(terminated, truncated).astype(values.dtype)
    deltas = rewards + gamma * not_term * next_values - values

    def body(adv_next, inp):
        delta, nd = inp
        adv = delta + gamma * lam * nd * adv_next
        return adv, adv

    _, advantages = jax.lax.scan(body, jnp.zeros_like(values[0]), (deltas, not_done), reverse=True)
    return advantages, advantages + values
