"""Bring your own memory: define a cell, check it against pobax's memory contract, run the T-Maze gap with it.

    python examples/custom_memory.py                        # T-Maze 5, 150k steps × 3 seeds per agent
    POBAX_EXAMPLE_TINY=1 python examples/custom_memory.py   # a smoke run: tiny networks, well under a minute

The report goes under `$POBAX_EXAMPLE_OUT` (default `runs/examples`), in `custom_memory-gap/`.
The same cell from the command line (its module must be importable): `PYTHONPATH=examples pobax gap --env tmaze_5
--memories custom_memory:DecayingTrace` (or `pobax train --memory custom_memory:DecayingTrace`).
"""

import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

from pobax.eval import format_gap, gap_report
from pobax.memory import AbstractMemory, Dense
from pobax.memory.testing import check_memory


class DecayingTrace(AbstractMemory):
    """`h_t = a ⊙ h_{t−1} + (1 − a) ⊙ tanh(W x_t + b)`, a learned decay per unit; `h` is reset to 0 at starts."""

    proj: Dense
    decay_logit: jax.Array
    in_size: int = eqx.field(static=True)  # every field that is not an array is static
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size: int, hidden_size: int, *, key):  # how pobax builds a cell
        self.in_size, self.out_size = in_size, hidden_size
        self.proj = Dense(in_size, hidden_size, key=key)
        self.decay_logit = jnp.linspace(0.0, 5.0, hidden_size)  # from fast (a = 0.5) to slow (a ≈ 0.99) traces

    def init_carry(self):
        return jnp.zeros(self.out_size)

    def __call__(self, carry, xs, starts):  # carry, (time, in_size) inputs, (time,) episode starts
        a = jax.nn.sigmoid(self.decay_logit)

        def step(h, inp):
            u, start = inp
            h = a * jnp.where(start, 0.0, h) + (1.0 - a) * u  # reset *before* the first input of an episode
            return h, h

        return jax.lax.scan(step, carry, (jnp.tanh(self.proj(xs)), starts))


if __name__ == "__main__":
    check_memory(DecayingTrace(5, 16, key=jax.random.key(0)))  # raises AssertionError naming what is broken
    print("DecayingTrace satisfies the memory contract")
    tiny = dict(total_steps=192, num_seeds=2, hidden_size=16, num_envs=4, num_steps=16, num_minibatches=2,
                num_chunks=1, fast_compile=True)
    overrides = tiny if os.environ.get("POBAX_EXAMPLE_TINY") == "1" else dict(total_steps=150_000, num_seeds=3)
    out = Path(os.environ.get("POBAX_EXAMPLE_OUT", "runs/examples")) / "custom_memory-gap"
    report = gap_report("tmaze_5", agents=("floor", "ceiling"), memories=("custom_memory:DecayingTrace",),
                        overrides=overrides, out=out)
    print(format_gap(report))
