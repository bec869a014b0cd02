"""The paper's recurrent memory: `Dense → ReLU → GRU` (optionally an extra dense layer, as for Battleship).

The input-side work (dense layers and the GRU's input projections) is computed for the whole sequence at
once; only the recurrent part runs in a `jax.lax.scan`. This keeps the sequential loop small, which is what
bounds PPO's replay speed on both CPU and GPU.
"""

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._backend import gru_impl
from ._base import AbstractMemory, check_inputs
from ._layers import MLP, NO_BATCH, expand_to, flat_draw, matmul_t, orthogonal, recurrent_matvec

#: How the GRU's time loop can be computed (`GRU`'s `impl`): "dot" (a `jax.lax.scan` whose recurrent product is a
#: matrix product), "reduce" (the same scan, the product as a broadcast multiply and sum, which XLA fuses with the gate
#: arithmetic), "fused" (the whole loop in one Pallas kernel per direction, `pobax.memory._gru_fused`: Triton on GPUs,
#: a slow interpreter on the CPU; where `fused_supported(T, H)` does not hold, e.g. the rollout's T = 1, the scan with
#: "dot"). The same function every way (float rounding aside; tested). "auto": the choice for `GRU`'s `platform`
#: (`pobax._backend.gru_impl`).
IMPLS = ("auto", "dot", "reduce", "fused")


class GRU(AbstractMemory[Float[Array, " hidden"]]):
    """`Dense(in, h) → ReLU → GRU(h, h)`; with `extra_dense`, `Dense(in, 2h) → ReLU → Dense(2h, h) → ReLU → GRU`.

    GRU update (PyTorch/Flax convention): `r = σ(W_ir x + W_hr h + b_r)`, `z = σ(W_iz x + W_hz h + b_z)`,
    `n = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn))`, `h' = (1 − z) ⊙ n + z ⊙ h`. The carry is reset to zeros
    before an input with `starts[t]` true.
    """

    pre: MLP
    weight_ih: Float[Array, "3*hidden hidden"]
    weight_hh: Float[Array, "3*hidden hidden"]
    bias: Float[Array, "3*hidden"]
    bias_hn: Float[Array, " hidden"]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)
    unroll: int = eqx.field(static=True)
    impl: str = eqx.field(static=True)
    platform: str = eqx.field(static=True)
    matmul_batch: tuple[int, int] = eqx.field(static=True)  # `matmul_t`'s batch (`with_matmul_batch`)

    def __init__(
        self,
        in_size: int,
        hidden_size: int,
        *,
        key: PRNGKeyArray,
        extra_dense: bool = False,
        unroll: int = 1,
        impl: str = "auto",
        platform: str = "cpu",
    ):
        if impl not in IMPLS:
            raise ValueError(f"GRU impl must be one of {', '.join(IMPLS)}, got {impl!r}.")
        k_pre, k_ih, k_hh = jax.random.split(key, 3)
        self.in_size = in_size
        self.out_size = hidden_size
        self.unroll = unroll
        self.platform = platform
        self.impl = gru_impl(hidden_size, platform) if impl == "auto" else impl
        self.matmul_batch = NO_BATCH
        h = hidden_size
        sizes = (in_size, 2 * h, h) if extra_dense else (in_size, h)
        self.pre = MLP(sizes, key=k_pre)
        lim = 1.0 / math.sqrt(h)
        self.weight_ih = flat_draw(jax.random.uniform, k_ih, (3 * h, h), minval=-lim, maxval=lim)
        # Orthogonal recurrent weights per gate (as Flax's GRUCell).
        self.weight_hh = jnp.concatenate(
            [orthogonal(k, (h, h)) for k in jax.random.split(k_hh, 3)]
        )
        self.bias = jnp.zeros((3 * h,), jnp.float32)
        self.bias_hn = jnp.zeros((h,), jnp.float32)

    def init_carry(self) -> Float[Array, " hidden"]:
        return jnp.zeros((self.out_size,), jnp.float32)

    def __call__(
        self, carry: Float[Array, " hidden"], xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[Float[Array, " hidden"], Float[Array, "time hidden"]]:
        check_inputs(self, xs, starts)
        x = jax.nn.relu(self.pre(xs))
        gates_x = matmul_t(x, self.weight_ih, self.matmul_batch) + expand_to(self.bias, 2)  # (time, 3h): no carry needed
        impl = self.impl
        if impl == "fused":
            from ._gru_fused import fused_recurrence, fused_supported  # Pallas is imported only when used

            if fused_supported(xs.shape[0], self.out_size):
                return fused_recurrence(self.weight_hh, self.bias_hn, gates_x, starts, carry,
                                        interpret=self.platform != "gpu")
            impl = "dot"
        return scan_recurrence(self.weight_hh, self.bias_hn, gates_x, starts, carry, impl=impl, unroll=self.unroll)


def scan_recurrence(
    weight_hh: Float[Array, "gates hidden"],
    bias_hn: Float[Array, " hidden"],
    gates_x: Float[Array, "time gates"],
    starts: Bool[Array, " time"],
    carry: Float[Array, " hidden"],
    *,
    impl: str = "dot",
    unroll: int = 1,
    vjp: str = "manual",
) -> tuple[Float[Array, " hidden"], Float[Array, "time hidden"]]:
    """The GRU's recurrent part as a `jax.lax.scan` over time, given the input projections `gates_x` (order r, z,
    n, biases included): the carry is reset to zeros before a step with `starts[t]`. `impl`: "dot" or "reduce"
    (how `weight_hh @ h` is computed, see `IMPLS`). `vjp`: how its gradient is computed: "manual" (`recurrence`,
    whose backward is a reverse scan that carries only the hidden state's gradient; the gradient of `weight_hh` is
    then one matrix product over time after the loop, which is what makes the GRU's replay fast on a GPU) or
    "autodiff" (JAX's transpose of the scan, which adds an outer product into a (3H, H) carry at every step; kept as
    the reference the tests compare with). Returns `(carry_out, ys)`."""
    loops = ScanLoops(impl, unroll)
    if vjp == "manual":
        return recurrence(loops, weight_hh, bias_hn, gates_x, starts, carry)
    if vjp != "autodiff":
        raise ValueError(f"scan_recurrence: vjp must be 'manual' or 'autodiff', not {vjp!r}")
    carry, ys, _ = loops.forward(False, weight_hh, bias_hn, gates_x, starts, carry)
    return carry, ys


@dataclasses.dataclass(frozen=True)
class ScanLoops:
    """The time loops of `recurrence` as `jax.lax.scan`s (`impl` "dot" or "reduce", see `IMPLS`)."""

    impl: str = "dot"
    unroll: int = 1

    def forward(self, save, weight_hh, bias_hn, gates_x, starts, carry):
        """`(carry_out, ys, saved)`; `saved` = the per-step `(r, z, n, W_hn h + b_hn)` if `save`, else None."""
        h = carry.shape[0]

        def step(hidden, inp):
            gx, start = inp
            hidden = jnp.where(start, jnp.zeros_like(hidden), hidden)
            gh = recurrent_matvec(self.impl, weight_hh, hidden)
            r = jax.nn.sigmoid(gx[:h] + gh[:h])
            z = jax.nn.sigmoid(gx[h : 2 * h] + gh[h : 2 * h])
            ghn = gh[2 * h :] + bias_hn
            n = jnp.tanh(gx[2 * h :] + r * ghn)
            new = (1.0 - z) * n + z * hidden
            return new, ((new, r, z, n, ghn) if save else new)

        carry_out, out = jax.lax.scan(step, carry, (gates_x, starts), unroll=self.unroll)
        return (carry_out, out[0], out[1:]) if save else (carry_out, out, None)

    def backward(self, weight_hh, keep, hprev, saved, dys, d_last):
        """The reverse loop: the gradients of the r, z and n pre-activations per step, and of the incoming carry."""
        r, z, n, ghn = saved
        h = d_last.shape[0]
        w_t = weight_hh.T

        def step(dh_next, inp):
            dy, r_t, z_t, n_t, ghn_t, hp_t, keep_t = inp
            dh = dy + dh_next
            da_n = dh * (1.0 - z_t) * (1.0 - n_t * n_t)
            da_r = da_n * ghn_t * r_t * (1.0 - r_t)
            da_z = dh * (hp_t - n_t) * z_t * (1.0 - z_t)
            dhp = dh * z_t + recurrent_matvec(self.impl, w_t, jnp.concatenate([da_r, da_z, da_n * r_t]))
            return keep_t * dhp, jnp.concatenate([da_r, da_z, da_n])

        dcarry, da = jax.lax.scan(step, d_last, (dys, r, z, n, ghn, hprev, keep), reverse=True, unroll=self.unroll)
        return da[:, :h], da[:, h : 2 * h], da[:, 2 * h :], dcarry


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def recurrence(loops, weight_hh, bias_hn, gates_x, starts, carry):
    """The GRU recurrence of one sequence (see `scan_recurrence`) with a hand-written gradient, whatever runs its
    time loops: `loops` (static, hashable) has `forward(save, weight_hh, bias_hn, gates_x, starts, carry) ->
    (carry_out, ys, saved)` (saved: per-step r, z, n and `W_hn h + b_hn`) and `backward(weight_hh, keep, hprev,
    saved, dys, d_last) -> (da_r, da_z, da_n, d_carry)` (keep: 0.0 at starts, else 1.0; hprev: the hidden state
    each step used). `ScanLoops` here, Pallas kernels in `pobax.memory._gru_fused`. Everything outside the loops
    is shared: the weight gradient is one matrix product over time, the bias and input gradients follow from the
    pre-activation gradients. Returns `(carry_out, ys)`."""
    carry_out, ys, _ = loops.forward(False, weight_hh, bias_hn, gates_x, starts, carry)
    return carry_out, ys


def _recurrence_fwd(loops, weight_hh, bias_hn, gates_x, starts, carry):
    carry_out, ys, saved = loops.forward(True, weight_hh, bias_hn, gates_x, starts, carry)
    return (carry_out, ys), (weight_hh, starts, carry, ys, saved)


def _recurrence_bwd(loops, res, cts):
    weight_hh, starts, carry, ys, saved = res
    d_last, dys = cts
    keep = jnp.where(starts, 0.0, 1.0).astype(ys.dtype)
    hprev = keep[:, None] * jnp.concatenate([carry[None, :].astype(ys.dtype), ys[:-1]], axis=0)
    da_r, da_z, da_n, d_carry = loops.backward(weight_hh, keep, hprev, saved, dys.astype(ys.dtype),
                                              d_last.astype(ys.dtype))
    d_ghn = da_n * saved[0]  # the gradient of W_hn h + b_hn: r ⊙ d(n pre-activation)
    d_gates_x = jnp.concatenate([da_r, da_z, da_n], axis=1)
    d_gh = jnp.concatenate([da_r, da_z, d_ghn], axis=1)
    d_weight_hh = d_gh.T @ hprev  # Σ_t outer(d_gh_t, h_{t-1})
    return d_weight_hh, jnp.sum(d_ghn, axis=0), d_gates_x, None, d_carry


recurrence.defvjp(_recurrence_fwd, _recurrence_bwd)
