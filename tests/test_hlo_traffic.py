"""`pobax._hlo`: bytes and kernels of a compiled program, loops multiplied by their trip counts."""

import jax
import jax.numpy as jnp

from pobax._hlo import traffic


def _hlo(f, *args) -> str:
    return jax.jit(f).lower(*args).compile().as_text()


def test_a_single_matmul_reads_its_operands_and_writes_its_result_once():
    t = traffic(_hlo(lambda a, b: a @ b, jnp.ones((256, 512)), jnp.ones((512, 128))))
    assert t["bytes"] == 4 * (256 * 512 + 512 * 128 + 256 * 128)
    assert t["loops"] == [] and t["uncounted_loops"] == 0


def test_a_scan_counts_its_body_per_step_and_only_the_rows_it_slices():
    n, steps = 1000, 10

    def f(x, xs):
        return jax.lax.scan(lambda c, row: (c * 2 + row, None), x, xs)[0]

    t = traffic(_hlo(f, jnp.ones(n), jnp.ones((steps, n))))
    assert t["loops"] == [(0, steps)] and t["uncounted_loops"] == 0
    per_step = 3 * 4 * n  # read the carry and one row, write the carry
    assert steps * per_step <= t["bytes"] < steps * per_step + 4 * 4 * n  # + copies around the loop
    assert t["bytes"] < steps * 4 * n * steps  # never the whole stacked input per step
    assert t["kernels"] >= steps


def test_scan_outputs_are_written_one_row_per_step_in_place():
    n, steps = 1000, 10

    def g(x):
        return jax.lax.scan(lambda c, _: (c * 2 + 1, c * 3), x, None, length=steps)[1]

    t = traffic(_hlo(g, jnp.ones(n)))
    stacked = 4 * n * steps
    # each step: the carry read for both results, the new carry and one output row written; plus filling the
    # stacked output once. Counting the whole stacked buffer at every step would be > steps * stacked.
    assert steps * 4 * 4 * n <= t["bytes"] <= steps * 8 * 4 * n + 2 * stacked


def test_both_branches_of_a_conditional_are_counted():
    x = jnp.ones((64, 64))

    def a(x):
        return jnp.sin(x) @ x.T

    def b(x):
        return jnp.cos(x).sum(0, keepdims=True) * x[:1].T

    alone = [traffic(_hlo(f, x)) for f in (a, b)]
    both = traffic(_hlo(lambda p, x: jax.lax.cond(p, a, b, x), True, x))
    assert both["bytes"] >= alone[0]["bytes"] + alone[1]["bytes"]
    assert both["kernels"] >= alone[0]["kernels"] + alone[1]["kernels"]
