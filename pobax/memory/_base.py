"""The memory contract: what every memory cell, built in or your own, does (the one statement of it; docs and
`pobax.memory.testing.check_memory`, which tests it, refer here).

A **memory cell** is an `equinox.Module` subclassing `pobax.memory.AbstractMemory` that maps a sequence of inputs
of *one* environment to a sequence of features, carrying state between calls:

    carry = cell.init_carry()                      # the state of a fresh episode (a pytree of arrays)
    carry, ys = cell(carry, xs, starts)            # xs: (time, in_size) floats; starts: (time,) bools
                                                   # ys: (time, out_size) floats; carry: like init_carry()

(`check_inputs(cell, xs, starts)` refuses other shapes in one line; the built-in cells call it first.)

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
import numpy as np
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



def check_inputs(cell: AbstractMemory, xs, starts) -> None:
    """Refuse, in one line, inputs that break the contract's shapes (the built-in cells call it first): `xs` an
    array of shape (time >= 1, in_size), `starts` a bool array of shape (time,). Without it one cell broadcast a
    (time, 1) `starts`, another read floats as starts, a third failed deep inside a scan. Shapes and dtypes are
    static, so this costs nothing under `jit` and sees one example's shapes under `vmap`."""
    name = f"{type(cell).__name__}(in_size={cell.in_size})"
    shape = getattr(xs, "shape", None)
    if shape is None or len(shape) != 2 or shape[0] < 1 or shape[1] != cell.in_size:
        raise ValueError(f"{name}: xs must be an array of shape (time >= 1, {cell.in_size}), got "
                         f"{shape if shape is not None else type(xs).__name__}; a cell sees one environment's sequence "
                         f"(vmap it over environments).")
    got = getattr(starts, "shape", None)
    if got != (shape[0],) or np.dtype(starts.dtype) != np.bool_:
        what = f"{starts.dtype} {got}" if got is not None else type(starts).__name__
        raise ValueError(f"{name}: starts must be a bool array of shape (time,) = ({shape[0]},), got {what}; pass "
                         f"e.g. `dones.astype(bool)` with one flag per input.")
