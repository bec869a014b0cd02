"""The memoryless baseline: the paper's 4-layer MLP, applied to each input independently."""

import equinox as eqx
import jax
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._base import AbstractMemory, check_inputs
from ._layers import MLP


class Memoryless(AbstractMemory[None]):
    """`Dense(in, h) → ReLU → Dense(h, h) → ReLU → Dense(h, h) → ReLU → Dense(h, h)`; the carry is `None`."""

    mlp: MLP
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray):
        self.in_size = in_size
        self.out_size = hidden_size
        self.mlp = MLP((in_size, hidden_size, hidden_size, hidden_size, hidden_size), key=key)

    def init_carry(self) -> None:
        return None

    def __call__(
        self, carry: None, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[None, Float[Array, "time out_size"]]:
        check_inputs(self, xs, starts)
        del starts  # nothing to reset
        # Output of the last dense layer goes through ReLU before the heads, like the other memories.
        return None, jax.nn.relu(self.mlp(xs))
