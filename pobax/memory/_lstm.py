"""Long short-term memory, laid out like pobax's GRU: `Dense → ReLU → LSTM`, input projections outside the loop."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._base import AbstractMemory
from ._layers import MLP, expand_to, matmul_t, orthogonal


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
    in a `jax.lax.scan` (sequential: `time` dependent steps).
    """

    pre: MLP
    weight_ih: Float[Array, "4*hidden hidden"]
    weight_hh: Float[Array, "4*hidden hidden"]
    bias: Float[Array, "4*hidden"]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray):
        k_pre, k_ih, k_hh = jax.random.split(key, 3)
        h = hidden_size
        self.in_size, self.out_size = in_size, h
        self.pre = MLP((in_size, h), key=k_pre)
        lim = 1.0 / math.sqrt(h)
        self.weight_ih = jax.random.uniform(k_ih, (4 * h, h), minval=-lim, maxval=lim)
        self.weight_hh = jnp.concatenate([orthogonal(k, (h, h)) for k in jax.random.split(k_hh, 4)])
        self.bias = jnp.zeros((4 * h,), jnp.float32).at[h : 2 * h].set(1.0)  # gate order i, f, g, o

    def init_carry(self) -> LSTMCarry:
        zeros = jnp.zeros((self.out_size,), jnp.float32)
        return LSTMCarry(h=zeros, c=zeros)

    def __call__(
        self, carry: LSTMCarry, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[LSTMCarry, Float[Array, "time hidden"]]:
        x = jax.nn.relu(self.pre(xs))
        gates_x = matmul_t(x, self.weight_ih) + expand_to(self.bias, 2)  # (time, 4h): all that needs no carry
        h = self.out_size

        def step(state, inp):
            gx, start = inp
            hid, cell = (jnp.where(start, jnp.zeros_like(v), v) for v in state)
            gates = gx + self.weight_hh @ hid
            i, f, o = (jax.nn.sigmoid(gates[k * h : (k + 1) * h]) for k in (0, 1, 3))
            g = jnp.tanh(gates[2 * h : 3 * h])
            cell = f * cell + i * g
            hid = o * jnp.tanh(cell)
            return (hid, cell), hid

        (hid, cell), ys = jax.lax.scan(step, (carry.h, carry.c), (gates_x, starts))
        return LSTMCarry(h=hid, c=cell), ys
