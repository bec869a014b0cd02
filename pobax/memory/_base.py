"""The memory contract: what every memory cell, built in or your own, does (the one statement of it; docs and
`pobax.memory.testing.check_memory`, which tests it, refer here).

A **memory cell** is an `equinox.Module` subclassing `pobax.memory.AbstractMemory` that maps a sequence of inputs
of *one* environment to a sequence of features, carrying state between calls:

    carry = cell.init_carry()                      # the state of a fresh episode (a pytree of arrays)
    carry, ys = cell(carry, xs, starts)            # xs: (time, in_size) floats; starts: (time,) bools
                                                   # ys: (time, out_size) floats; carry: like init_carry()

- **Unbatched.** A cell sees one environment's sequence; pobax `vmap`s it over environments, over minibatch
  sequences and over runs (seeds × hyperparameter sets, whose parameters differ).
- **Episode resets through `starts`.** `starts[t]` true means input `t` is the first of a new episode: the carry
  is reset to `init_carry()` *before* input `t` is processed. Nothing of an earlier episode may reach an output at
  or after a start, nor (through the carry returned) any later output; a carry may keep stale values (e.g. masked
  ones) that never reach an output, as the Transformer-XL's cache does.
- **Chunking does not matter.** Rollouts call the cell with `time == 1`, the PPO replay calls it once over a
  whole segment from the carry saved at the segment's start, evaluation steps one at a time: one step at a time,
  or any split of a sequence into consecutive calls, must give the outputs and final carry of one call over the
  whole sequence (up to float rounding). The carry keeps its structure, shapes and dtypes from call to call.
- **Hyperparameters are fields.** Every field that is not a JAX array (sizes, flags, function choices) is
  `eqx.field(static=True)`: the whole network is created under `jax.vmap` (one per seed) and lives in a jitted
  training state, so its leaves must be arrays.
- `in_size` and `out_size` (ints) are the input and feature widths. Built into pobax's network (`--memory
  package.module:ClassName`), a cell class is constructed as `ClassName(in_size, hidden_size, key=key)` and its
  features (`out_size` wide) feed the actor and critic heads.
- Truncated backpropagation is the cell's choice: PPO replays a segment from a saved carry, so gradients never
  reach earlier segments anyway.
"""

from typing import Generic, TypeVar

import equinox as eqx
from jaxtyping import Array, Bool, Float

C = TypeVar("C")


class AbstractMemory(eqx.Module, Generic[C]):
    """Base class of memory cells: `init_carry()` and `__call__(carry, xs, starts)`, as the module's docstring states."""

    in_size: eqx.AbstractVar[int]
    out_size: eqx.AbstractVar[int]

    def init_carry(self) -> C:
        raise NotImplementedError

    def __call__(
        self, carry: C, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[C, Float[Array, "time out_size"]]:
        raise NotImplementedError

