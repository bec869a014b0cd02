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
    *,
    method: str = "auto",
) -> tuple[Float[Array, "time *batch"], Float[Array, "time *batch"]]:
    """Advantages and value targets (`advantages + values`).

    `method` (the same values up to float rounding; tested): "weights", the recursion unrolled into one weighted sum
    per step (`_weighted_sum`, no loop); "associative", `jax.lax.associative_scan` (log-depth); "sequential", a
    reverse `jax.lax.scan` of T dependent steps; "auto", "weights" up to `WEIGHTS_MAX_T` steps (its work grows with
    T²), else "associative"; on GPUs both train faster than "sequential" (compare the three:
    `python benchmarks/profile_update.py --cases tmaze_10:gru:30 --gae-method METHOD`).

    Inputs of other shapes (they would broadcast into another array), non-boolean flags (a flag of 2 would make
    1 - flag negative), a γ or λ given as a number outside [0, 1] and another `method` are refused (ValueError)."""
    if method not in METHODS:
        raise ValueError(f"gae: method must be one of {', '.join(map(repr, METHODS))}, got {method!r}.")
    rewards, values, next_values, terminated, truncated = map(
        jnp.asarray, (rewards, values, next_values, terminated, truncated))
    shapes = {name: x.shape for name, x in zip(("rewards", "values", "next_values", "terminated", "truncated"),
                                               (rewards, values, next_values, terminated, truncated))}
    if len(set(shapes.values())) != 1 or not rewards.ndim:
        got = ", ".join(f"{k} {v}" for k, v in shapes.items())
        raise ValueError(f"gae: every input has one shape, (time, *batch), got {got}.")
    if terminated.dtype != bool or truncated.dtype != bool:
        raise ValueError(f"gae: terminated and truncated are boolean arrays, got {terminated.dtype} and "
                         f"{truncated.dtype} (pass x.astype(bool)).")
    for name, x in (("gamma", gamma), ("lam", lam)):
        if isinstance(x, int | float) and not 0.0 <= x <= 1.0:
            raise ValueError(f"gae: {name} must be in [0, 1], got {x}.")
    not_term = 1.0 - terminated.astype(values.dtype)
    not_done = 1.0 - jnp.logical_or(terminated, truncated).astype(values.dtype)
    deltas = rewards + gamma * not_term * next_values - values
    if method == "auto":
        method = "weights" if deltas.shape[0] <= WEIGHTS_MAX_T else "associative"
    coeffs = gamma * lam * not_done
    if method == "weights":
        advantages = _weighted_sum(deltas, not_done, gamma * lam)
    elif method == "sequential":
        def body(adv_next, inp):
            delta, c = inp
            adv = delta + c * adv_next
            return adv, adv

        _, advantages = jax.lax.scan(body, jnp.zeros_like(values[0]), (deltas, coeffs), reverse=True)
    else:
        # A_t = δ_t + c_t A_{t+1} composes affine maps x ↦ δ + c x; their composition is associative, so the
        # recursion runs as a parallel prefix scan of depth log2(T) instead of T dependent steps.
        def compose(later, earlier):  # `earlier` is applied to the result of `later` (reverse=True order)
            c_l, d_l = later
            c_e, d_e = earlier
            return c_e * c_l, d_e + c_e * d_l

        _, advantages = jax.lax.associative_scan(compose, (coeffs, deltas), reverse=True, axis=0)
    return advantages, advantages + values


def _weighted_sum(deltas, not_done, gl):
    """The recursion unrolled: A_t = Σ_{s≥t} (γλ)^(s−t) δ_s over the steps s of t's episode, i.e. those with no
    episode end at t, …, s−1. Episode ends are counted with a cumulative sum (E_s = ends before step s), so "same
    episode" is E_s = E_t. One multiply–reduce over a (T, T) weight per environment, without a loop; only for
    short rollouts (`WEIGHTS_MAX_T`), as its work grows with T²."""
    T = deltas.shape[0]
    ends = (1.0 - not_done).astype(jnp.int32)
    before = jnp.cumsum(ends, axis=0) - ends  # E_s: episode ends at steps < s
    t = jnp.arange(T)
    lag = t[None, :] - t[:, None]  # [t, s] = s − t
    decay = jnp.where(lag >= 0, jnp.power(gl, jnp.maximum(lag, 0).astype(deltas.dtype)), 0.0)
    extra = (1,) * (deltas.ndim - 1)
    same = before[None, :] == before[:, None]  # [t, s, *batch]
    w = jnp.where(same, decay.reshape(decay.shape + extra), 0.0)
    return jnp.sum(w * deltas[None], axis=1)


#: The longest rollout for which `gae`'s "auto" uses "weights" (its work is T² per environment).
WEIGHTS_MAX_T = 256
#: `gae`'s methods.
METHODS = ("auto", "weights", "associative", "sequential")
