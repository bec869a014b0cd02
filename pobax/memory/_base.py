"""The memory contract shared by every memory cell.

A memory maps a sequence of inputs to a sequence of features, carrying state across calls:

    carry, ys = memory(carry, xs, starts)

`starts[t]` is true when input `t` is the first of a new episode: the memory is reset to
`init_carry()` *before* processing input `t`. Rollouts call it with `time == 1`; training replays a whole
segment from the carry saved at the segment's start; evaluation steps one at a time. Because the reset is
inside the memory, all three see exactly the same computation (tests/test_memory.py proves it).
"""

from typing import Generic, TypeVar

import equinox as eqx
from jaxtyping import Array, Bool, Float, PyTree

C = TypeVar("C")


class AbstractMemory(eqx.Module, Generic[C]):
    """Base class of memory cells: `init_carry()` and `__call__(carry, xs, starts)`."""

    in_size: eqx.AbstractVar[int]
    out_size: eqx.AbstractVar[int]

    def init_carry(self) -> C:
        raise NotImplementedError

    def __call__(
        self, carry: C, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[C, Float[Array, "time out_size"]]:
        raise NotImplementedError


def stop_gradient_carry(carry: PyTree) -> PyTree:
    """Truncated backpropagation: no gradient flows into a saved carry."""
    import jax

    return jax.tree.map(jax.lax.stop_gradient, carry)
