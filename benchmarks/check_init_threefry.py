"""The initial training state is the same whether `_init` is compiled with JAX's threefry kernel (the GPU default,
`pobax.agent._train.INIT_THREEFRY_KERNEL`) or with XLA's inlined hash: prints the largest difference per case.

    python benchmarks/check_init_threefry.py --cases tmaze_10:gru:3 battleship_10:gru:2
"""

import argparse
import dataclasses
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import pobax.agent._train as train_mod  # noqa: E402
from bench_train import case_config  # noqa: E402
from pobax.env import make  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["tmaze_10:gru:3"])
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}")
    if jax.default_backend() != "gpu":
        print("not a GPU: both runs use XLA's hash here, so the difference is 0 by construction; run it on a GPU")
    for case in args.cases:
        env_id, memory, seeds = case.split(":")
        cfg = dataclasses.replace(case_config(env_id, memory, int(seeds), updates=4), seed=7)
        env = make(cfg.env, cfg.observability, action_concat=cfg.action_concat)
        states = []
        for kernel in (True, False):
            train_mod.INIT_THREEFRY_KERNEL = kernel
            jax.clear_caches()
            states.append(eqx.filter(train_mod._init(cfg, env, np.arange(int(seeds))), eqx.is_array))
        numbers = [[jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x
                    for x in jax.tree.leaves(st)] for st in states]
        leaves = [float(jnp.max(jnp.abs(jnp.asarray(a, jnp.float32) - jnp.asarray(b, jnp.float32))))
                  for a, b in zip(*numbers)]
        print(f"{case}: {len(leaves)} arrays, largest difference {max(leaves):.3g}")


if __name__ == "__main__":
    main()
