"""Fast and forgetful memory in real arithmetic: `Dense(in, h) → ReLU → FFM`, replayed by one associative scan.

Morad, Kortvelesy, Liwicki & Prorok, "Reinforcement Learning with Fast and Forgetful Memory", NeurIPS 2023
(arXiv:2310.04128). The same function and initialisation as memax's `FFM` (Morad et al., github.com/smorad/memax),
which pobax used first: under one key both build the same weights, and their outputs agree to float rounding
(`tests/test_memory_zoo.py`). Written here to be fast where pobax trains (docs/memories.md, "Throughput"): the three
input projections are one matrix product, both products are `matmul_t` (one fused multiply-sum per rollout step),
and the recurrence is the LRU's `complex_affine_scan` in real arithmetic with its adjoint backward.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._base import AbstractMemory, check_inputs
from ._layers import MLP, NO_BATCH, expand_to, matmul_t
from ._lru import complex_affine_scan

FFMCarry = tuple[Float[Array, "trace context"], Float[Array, "trace context"]]  # the complex state: (real, imag)


def _linear(key: PRNGKeyArray, in_size: int, out_size: int) -> tuple[Array, Array]:
    """Equinox's `nn.Linear` initialisation (weight and bias uniform in ±1/√in), as memax's layers have it."""
    layer = eqx.nn.Linear(in_size, out_size, key=key)
    return layer.weight, layer.bias


class FFM(AbstractMemory[FFMCarry]):
    """Fast and forgetful memory: Morad, Kortvelesy, Liwicki & Prorok, "Reinforcement Learning with Fast and
    Forgetful Memory", NeurIPS 2023 (arXiv:2310.04128).

    `Dense(in, h) → ReLU` gives `u_t`; an input-gated projection `x_t = W_x u_t ⊙ σ(W_g u_t)` to `trace_size`
    traces is accumulated into a complex state of `trace_size × context_size`, decayed per trace (`exp(−|α|)`) and
    rotated per context frequency (`exp(iω)`, periods 1 to 10,000 steps) every step: `S_t = γ ⊙ S_{t−1} + x_t`
    (an episode start forgets `S_{t−1}`). The output mixes the real and imaginary parts of `S_t` back to
    `hidden_size`, gated against the input: `y_t = LayerNorm(Mix(S_t) ⊙ g_t) + u_t ⊙ (1 − g_t)`, `g_t = σ(W_o u_t)`.
    The carry is the state `(re, im)`; replay is an associative scan.
    """

    pre: MLP
    w_in: Float[Array, "proj hidden"]  # rows: W_x (trace), W_g (trace), W_o (hidden)
    b_in: Float[Array, " proj"]
    alpha: Float[Array, " trace"]  # decay rate per trace: |γ| = exp(−|α|)
    omega: Float[Array, " context"]  # angular frequency per context: arg γ = ω
    w_mix: Float[Array, "hidden state"]  # from [Re S, Im S] per trace, flattened
    b_mix: Float[Array, " hidden"]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)
    trace_size: int = eqx.field(static=True)
    context_size: int = eqx.field(static=True)
    matmul_batch: tuple[int, int] = eqx.field(static=True)  # `matmul_t`'s batch (`with_matmul_batch`)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray, trace_size: int = 32,
                 context_size: int = 4, min_period: float = 1.0, max_period: float = 10_000.0):
        k_pre, k_cell = jax.random.split(key)
        k_x, k_g, k_o, _, k_mix, _ = jax.random.split(k_cell, 6)  # memax's order of keys
        h = hidden_size
        self.in_size, self.out_size, self.trace_size, self.context_size = in_size, h, trace_size, context_size
        self.pre = MLP((in_size, h), key=k_pre)
        (wx, bx), (wg, bg), (wo, bo) = _linear(k_x, h, trace_size), _linear(k_g, h, trace_size), _linear(k_o, h, h)
        self.w_in, self.b_in = jnp.concatenate([wx, wg, wo], 0), jnp.concatenate([bx, bg, bo], 0)
        self.alpha = jnp.linspace(1e-6, 0.5, trace_size)
        self.omega = 2 * jnp.pi / jnp.linspace(min_period, max_period, context_size)
        self.w_mix, self.b_mix = _linear(k_mix, 2 * trace_size * context_size, h)
        self.matmul_batch = NO_BATCH

    def init_carry(self) -> FFMCarry:
        shape = (self.trace_size, self.context_size)
        return jnp.zeros(shape, jnp.float32), jnp.zeros(shape, jnp.float32)

    def __call__(
        self, carry: FFMCarry, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[FFMCarry, Float[Array, "time out_size"]]:
        check_inputs(self, xs, starts)
        u = jax.nn.relu(self.pre(xs))
        m = self.trace_size
        proj = matmul_t(u, self.w_in, self.matmul_batch) + expand_to(self.b_in, 2)
        x = proj[:, :m] * jax.nn.sigmoid(proj[:, m:2 * m])  # (time, trace)
        gate = jax.nn.sigmoid(proj[:, 2 * m:])  # (time, hidden)
        modulus = jnp.exp(-jnp.abs(self.alpha))[:, None]
        keep = jnp.where(starts, 0.0, 1.0)[:, None, None]  # an episode start forgets the state before it
        a_re = keep * (modulus * jnp.cos(self.omega)[None, :])[None]
        a_im = keep * (modulus * jnp.sin(self.omega)[None, :])[None]
        b_re = jnp.broadcast_to(x[:, :, None], a_re.shape)
        s_re, s_im = complex_affine_scan((a_re, a_im), (b_re, jnp.zeros_like(b_re)), carry)
        z = jnp.concatenate([s_re, s_im], -1).reshape(xs.shape[0], -1)  # per trace: Re S over contexts, then Im S
        z = (matmul_t(z, self.w_mix, self.matmul_batch) + expand_to(self.b_mix, 2)) * gate
        mean = jnp.mean(z, -1, keepdims=True)
        var = jnp.mean(jnp.square(z - mean), -1, keepdims=True)
        ys = (z - mean) * jax.lax.rsqrt(var + 1e-5) + u * (1 - gate)
        return (s_re[-1], s_im[-1]), ys
