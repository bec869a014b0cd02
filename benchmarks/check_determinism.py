"""Is a training run reproducible? A case (`bench_train.py`'s ENV:MEMORY:SEEDS at the paper's settings; default
RockSample 11 GRU, 1 seed), 40 updates, trained three times in this process: twice with the same compiled program, then once more after `clear_compiled()` (compiled again).
Prints the largest difference between the final weights of the first run and each of the other two, and a checksum
of the weights: run the script in several processes to compare across processes (each compiles afresh; set
`POBAX_COMPILE_CACHE=off` so none loads another's program). On a GPU the program's GEMMs follow
`pobax.agent._train.CUBLAS_MIN_HIDDEN` and `TILING_MAX_HIDDEN` unless `XLA_FLAGS` says otherwise.

    POBAX_COMPILE_CACHE=off python benchmarks/check_determinism.py --case battleship_10:gru:1
"""

import argparse
import os
import sys

import equinox as eqx
import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import pobax.agent._train as T
from pobax.agent import train


def main():
    from bench_train import case_config, parse_case  # noqa: PLC0415

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", default="rocksample_11_11:gru:1")
    env_id, memory, seeds, grid, obs = parse_case(p.parse_args().case)
    cfg = case_config(env_id, memory, seeds, 40, None, *obs, grid=grid)

    def weights(r):
        return np.concatenate([np.ravel(x) for x in jax.tree.leaves(eqx.filter(r.state.model, eqx.is_array))])

    a = weights(train(cfg, save=False, progress=False))
    b = weights(train(cfg, save=False, progress=False))  # the same executable
    T.clear_compiled()
    c = weights(train(cfg, save=False, progress=False))  # compiled again
    print(f"device: {jax.devices()[0].device_kind}, jax {jax.__version__}")
    print(f"same executable: max|diff| {np.abs(a - b).max()} | recompiled: {np.abs(a - c).max()} | "
          f"checksum {float(a.astype(np.float64).sum())!r}")


if __name__ == "__main__":
    main()
