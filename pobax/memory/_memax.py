"""A memory whose recurrence is associative, from the memax library (Morad et al., github.com/smorad/memax):
`Dense(in, h) → ReLU → memax cell`, behind pobax's memory contract.

memax's cells take `(carry, (xs, starts))` and reset the carry before an input whose start flag is set, as
pobax's `starts` do: the reset is folded into the associative operator (an element whose span contains a start
discards what comes before it; Morad et al., "Recurrent Reinforcement Learning with Memoroids", NeurIPS 2024), so
one `jax.lax.associative_scan` replays a sequence with resets in `O(log time)` depth. memax returns the state at
every step; the carry pobax keeps is the last one. `tests/test_memory_zoo.py` checks each cell against the
contract (`pobax.memory.testing.check_memory`).

memax keeps sizes and functions as ordinary fields; pobax creates networks under `jax.vmap`, where every leaf must be
an array, so each wrapper holds the memax cell split in two: its arrays (`arrays`, trained) and everything else
(`rest`, a static field). memax is imported when a cell is created, never by `import pobax` (its import creates JAX
arrays, which would initialise the backend).
"""

import equinox as eqx
import jax
from jaxtyping import Array, Bool, Float, PRNGKeyArray, PyTree

from ._base import AbstractMemory, check_inputs
from ._layers import MLP


class _MemaxMemory(AbstractMemory[PyTree]):
    """`Dense(in, h) → ReLU → cell`, the cell one of memax's (`_build`); `out_size == hidden_size`."""

    pre: MLP
    arrays: eqx.Module  # the memax cell's arrays (None elsewhere)
    rest: eqx.Module = eqx.field(static=True)  # the memax cell's other fields (None where arrays are)
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def _setup(self, in_size: int, hidden_size: int, key: PRNGKeyArray, build) -> None:
        k_pre, k_cell = jax.random.split(key)
        self.in_size, self.out_size = in_size, hidden_size
        self.pre = MLP((in_size, hidden_size), key=k_pre)
        self.arrays, self.rest = eqx.partition(build(k_cell), eqx.is_array)

    def _cell(self):
        return eqx.combine(self.arrays, self.rest)

    def init_carry(self) -> PyTree:
        return self._cell().initialize_carry()

    def __call__(
        self, carry: PyTree, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[PyTree, Float[Array, "time out_size"]]:
        check_inputs(self, xs, starts)
        cell = self._cell()
        states, ys = cell(carry, (jax.nn.relu(self.pre(xs)), starts))
        return cell.latest_recurrent_state(states), ys


class S6(_MemaxMemory):
    """Selective state-space model (S6, the recurrence of Mamba): Gu & Dao, "Mamba: Linear-Time Sequence Modeling
    with Selective State Spaces", 2023 (arXiv:2312.00752). memax's `S6`.

    A real diagonal recurrence whose discretisation depends on the input ("selective"): a step size
    `Δ_t = softplus(W_Δ u_t + b_Δ)`, `Ā_t = exp(Δ_t ⊙ A)` with `A = −exp(A_log)`, `B̄_t = (Ā_t − 1) / A ⊙ B(u_t)` (zero-
    order hold), `x_t = Ā_t ⊙ x_{t−1} + B̄_t ⊙ u_t`, `y_t = C(u_t) ⊙ x_t`. One state unit per feature (memax's
    simplification of Mamba's `N` states per channel; no convolution or gating block around it). The carry is
    memax's `((Π Ā, x), reset flag)`; replay is an associative scan.
    """

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray):
        from memax.equinox.semigroups.s6 import S6 as MemaxS6  # noqa: PLC0415

        self._setup(in_size, hidden_size, key, lambda k: MemaxS6(hidden_size, hidden_size, k))
