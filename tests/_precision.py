"""References at a stated precision, for tests that compare an implementation with one."""

import jax

#: Relative error bound of a matrix product's inputs at JAX's default precision on a GPU: TF32 keeps 10 mantissa bits,
#: so each input is rounded by at most 2^-11 and a product of two by at most 2^-10.
TF32_EPS = 2.0**-10


def at_float32_precision(run):
    """`run` (a jitted function) called with matrix products at float32 precision
    (`jax.default_matmul_precision("highest")`, part of the trace: the first call, inside, traces it so)."""
    def call(*args):
        with jax.default_matmul_precision("highest"):
            return run(*args)

    return call
