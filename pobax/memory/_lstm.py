"""Long short-term memory, laid out like pobax's GRU: `Dense → ReLU → LSTM`, input projections outside the loop."""

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._backend import lstm_impl, recurrent_product
from ._base import AbstractMemory, check_inputs
from ._layers import MLP, NO_BATCH, expand_to, flat_draw, matmul_t, orthogonal, recurrent_matvec

#: How an LSTM runs its time loop: "auto" (the choice for `LSTM`'s `platform`, `pobax._backend.lstm_impl`), "dot" or "reduce" (a
#: `jax.lax.scan` whose recurrent product is a matrix product or a multiply-sum fused with the gate arithmetic), or
#: "fused" (the whole loop in one Pallas kernel per direction, `pobax.memory._lstm_fused`: Triton on GPUs, a slow
#: interpreter on the CPU; where `fused_supported(T, H)` does not hold, e.g. the rollout's T = 1, the scan).
IMPLS = ("auto", "dot", "reduce", "fused")


class LSTMCarry(eqx.Module):
    """What an LSTM remembers: the output `h` and the cell state `c`."""

    h: Float[Array, " hidden"]
    c: Float[Array, " hidden"]


class LSTM(AbstractMemory[LSTMCarry]):
    """`Dense(in, h) → ReLU → LSTM(h, h)`: long short-term memory (Hochreiter & Schmidhuber, "Long Short-Term
    Memory", Neural Computation 9(8), 1997) with the forget gate of Gers, Schmidhuber & Cummins ("Learning to Forget:
    Continual Prediction with LSTM", Neural Computation 12(10), 2000).

    `i, f, o = σ(W_i· x + U_i· h + b_i·)`, `g = tanh(W_g x + U_g h + b_g)`, `c' = f ⊙ c + i ⊙ g`,
    `h' = o ⊙ tanh(c')`; the output is `h'`. The forget gate's bias starts at 1 (Jozefowicz et al., 2015), the
    recurrent weights are orthogonal per gate (as the GRU's). Both `h` and `c` are reset to zeros before an input
    with `starts[t]` true. The input projections of the whole sequence are one product; only the recurrent part runs
    in a sequential loop over time with a hand-written gradient (`lstm_recurrence`): a `jax.lax.scan`, or on GPUs
    up to 32 wide one Pallas kernel per direction (`impl` "fused", `pobax.memory._lstm_fused`). `platform`, `impl`
    and `unroll` as the GRU's (`pobax.memory.GRU`).
    """

    pre: MLP
    weight_ih: Float[Array, "4*hidden hidden"]
    weight_hh: Float[Array, "4*hidden hidden"]
    bias: Float[Array, "4*hidden"]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)
    unroll: int = eqx.field(static=True)
    impl: str = eqx.field(static=True)
    platform: str = eqx.field(static=True)
    matmul_batch: tuple[int, int] = eqx.field(static=True)  # `matmul_t`'s batch (`with_matmul_batch`)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray, unroll: int = 1, impl: str = "auto",
                 platform: str = "cpu"):
        if impl not in IMPLS:
            raise ValueError(f"LSTM impl must be one of {', '.join(IMPLS)}, got {impl!r}.")
        k_pre, k_ih, k_hh = jax.random.split(key, 3)
        h = hidden_size
        self.in_size, self.out_size, self.unroll = in_size, h, unroll
        self.platform = platform
        self.impl = lstm_impl(h, platform) if impl == "auto" else impl
        self.matmul_batch = NO_BATCH
        self.pre = MLP((in_size, h), key=k_pre)
        lim = 1.0 / math.sqrt(h)
        self.weight_ih = flat_draw(jax.random.uniform, k_ih, (4 * h, h), minval=-lim, maxval=lim)
        self.weight_hh = jnp.concatenate([orthogonal(k, (h, h)) for k in jax.random.split(k_hh, 4)])
        self.bias = jnp.zeros((4 * h,), jnp.float32).at[h : 2 * h].set(1.0)  # gate order i, f, g, o

    def init_carry(self) -> LSTMCarry:
        zeros = jnp.zeros((self.out_size,), jnp.float32)
        return LSTMCarry(h=zeros, c=zeros)

    def __call__(
        self, carry: LSTMCarry, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[LSTMCarry, Float[Array, "time hidden"]]:
        check_inputs(self, xs, starts)
        x = jax.nn.relu(self.pre(xs))
        gates_x = matmul_t(x, self.weight_ih, self.matmul_batch) + expand_to(self.bias, 2)  # (time, 4h): all that needs no carry
        impl = self.impl
        if impl == "fused":
            from ._gru_fused import fused_supported  # Pallas is imported only when used

            if fused_supported(xs.shape[0], self.out_size):
                from ._lstm_fused import fused_lstm_recurrence

                hid, cell, ys = fused_lstm_recurrence(self.weight_hh, gates_x, starts, carry.h, carry.c,
                                                      interpret=self.platform != "gpu")
                return LSTMCarry(h=hid, c=cell), ys
            impl = recurrent_product(self.out_size, self.platform, gates=4)  # the rollout's one step, or sizes the kernels do not take
        hid, cell, ys = lstm_recurrence(self.weight_hh, gates_x, starts, carry.h, carry.c, unroll=self.unroll,
                                         impl=impl)
        return LSTMCarry(h=hid, c=cell), ys


def lstm_recurrence(
    weight_hh: Float[Array, "gates hidden"],
    gates_x: Float[Array, "time gates"],
    starts: Bool[Array, " time"],
    h0: Float[Array, " hidden"],
    c0: Float[Array, " hidden"],
    *,
    vjp: str = "manual",
    unroll: int = 1,
    impl: str = "dot",
) -> tuple[Float[Array, " hidden"], Float[Array, " hidden"], Float[Array, "time hidden"]]:
    """The LSTM's recurrent part over one sequence as a `jax.lax.scan`, given the input projections `gates_x` (order
    i, f, g, o, biases included); `h` and `c` are reset to zeros before a step with `starts[t]`; `unroll`: of the
    time loops (`pobax._backend.default_unroll`, as for the GRU); `impl`: how `weight_hh @ h` is
    computed, "dot" (a matrix product) or "reduce" (a broadcast multiply and sum, which XLA fuses with the gate
    arithmetic: the choice on accelerators from 33 up to 221 wide for the LSTM, `pobax._backend.lstm_impl`).
    Returns `(h_last, c_last, ys)`.

    `vjp`: "manual" (`recurrence`: the backward is a reverse loop that carries only the gradients of `h` and `c`;
    the gradient of `weight_hh` is one matrix product over time after the loop) or "autodiff" (JAX's transpose of
    the scan, which adds an outer product into a (4H, H) carry at every step: the tests' reference). As for the
    GRU (`pobax.memory._gru.scan_recurrence`), the manual gradient is what makes the LSTM fast on a GPU
    (docs/performance.md)."""
    if impl not in ("dot", "reduce"):
        raise ValueError(f"lstm_recurrence: impl must be 'dot' or 'reduce', not {impl!r}")
    loops = ScanLoops(impl, unroll)
    if vjp == "manual":
        return recurrence(loops, weight_hh, gates_x, starts, h0, c0)
    if vjp != "autodiff":
        raise ValueError(f"lstm_recurrence: vjp must be 'manual' or 'autodiff', not {vjp!r}")
    h_last, c_last, ys, _ = loops.forward(False, weight_hh, gates_x, starts, h0, c0)
    return h_last, c_last, ys


@dataclasses.dataclass(frozen=True)
class ScanLoops:
    """The time loops of `recurrence` as `jax.lax.scan`s (`impl` "dot" or "reduce", see `IMPLS`)."""

    impl: str = "dot"
    unroll: int = 1

    def forward(self, save, weight_hh, gates_x, starts, h0, c0):
        """`(h_last, c_last, ys, saved)`; `saved` = the per-step gates `(i, f, g, o)` and the cell each step started
        from (after its reset) if `save`, else None."""
        h = h0.shape[0]

        def step(state, inp):
            gx, start = inp
            hid, cell = (jnp.where(start, jnp.zeros_like(v), v) for v in state)
            gates = gx + recurrent_matvec(self.impl, weight_hh, hid)
            i, f, o = (jax.nn.sigmoid(gates[k * h : (k + 1) * h]) for k in (0, 1, 3))
            g = jnp.tanh(gates[2 * h : 3 * h])
            new_cell = f * cell + i * g
            new_hid = o * jnp.tanh(new_cell)
            return (new_hid, new_cell), ((new_hid, i, f, g, o, cell) if save else new_hid)

        (h_last, c_last), out = jax.lax.scan(step, (h0, c0), (gates_x, starts), unroll=self.unroll)
        return (h_last, c_last, out[0], out[1:]) if save else (h_last, c_last, out, None)

    def backward(self, weight_hh, keep, saved, dys, dh_last, dc_last):
        """The reverse loop: the gradients of the gate pre-activations per step, `(T, 4H)` in the order i, f, g, o,
        and of the incoming `h` and `c`."""
        i, f, g, o, cell_in = saved
        w_t = weight_hh.T

        def step(state, inp):
            dh_next, dc_next = state
            dy, i_t, f_t, g_t, o_t, c_in, keep_t = inp
            dh = dy + dh_next
            tc = jnp.tanh(f_t * c_in + i_t * g_t)
            dc = dc_next + dh * o_t * (1.0 - tc * tc)
            da = jnp.concatenate([dc * g_t * i_t * (1.0 - i_t), dc * c_in * f_t * (1.0 - f_t),
                                  dc * i_t * (1.0 - g_t * g_t), dh * tc * o_t * (1.0 - o_t)])
            return (keep_t * recurrent_matvec(self.impl, w_t, da), keep_t * (dc * f_t)), da

        (dh0, dc0), da = jax.lax.scan(step, (dh_last, dc_last), (dys, i, f, g, o, cell_in, keep), reverse=True,
                                      unroll=self.unroll)
        return da, dh0, dc0


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def recurrence(loops, weight_hh, gates_x, starts, h0, c0):
    """The LSTM recurrence of one sequence (see `lstm_recurrence`) with a hand-written gradient, whatever runs its
    time loops: `loops` (static, hashable) has `forward(save, weight_hh, gates_x, starts, h0, c0) -> (h_last, c_last,
    ys, saved)` (saved: per-step i, f, g, o and the cell each step started from) and `backward(weight_hh, keep,
    saved, dys, dh_last, dc_last) -> (da, dh0, dc0)` (keep: 0.0 at starts, else 1.0; da: the gate pre-activations'
    gradients, (T, 4H)). `ScanLoops` here, Pallas kernels in `pobax.memory._lstm_fused`. The weight gradient is one
    matrix product over time after the loops. Returns `(h_last, c_last, ys)`."""
    h_last, c_last, ys, _ = loops.forward(False, weight_hh, gates_x, starts, h0, c0)
    return h_last, c_last, ys


def _recurrence_fwd(loops, weight_hh, gates_x, starts, h0, c0):
    h_last, c_last, ys, saved = loops.forward(True, weight_hh, gates_x, starts, h0, c0)
    return (h_last, c_last, ys), (weight_hh, starts, h0, ys, saved)


def _recurrence_bwd(loops, res, cts):
    weight_hh, starts, h0, ys, saved = res
    dh_last, dc_last, dys = cts
    keep = jnp.where(starts, 0.0, 1.0).astype(ys.dtype)
    da, dh0, dc0 = loops.backward(weight_hh, keep, saved, dys, dh_last, dc_last)
    hprev = keep[:, None] * jnp.concatenate([h0[None, :].astype(ys.dtype), ys[:-1]], axis=0)
    return da.T @ hprev, da, None, dh0, dc0  # Σ_t outer(da_t, h_{t-1}): one product after the loop


recurrence.defvjp(_recurrence_fwd, _recurrence_bwd)
