"""Is a training run reproducible? RockSample 11 GRU, 1 seed, 40 updates at the paper's sizes, trained three times in
this process: twice with the same compiled program, then once more after `clear_compiled()` (compiled again).
Prints the largest difference between the final weights of the first run and each of the other two, and a checksum
of the weights: run the script in several processes to compare across processes (each compiles afresh; set
`POBAX_COMPILE_CACHE=off` so none loads another's program). On a GPU the program's GEMM backend follows
`pobax.agent._train.CUBLAS_MIN_HIDDEN` / `CUBLAS_OPTIONS` unless `XLA_FLAGS` says otherwise.

    POBAX_COMPILE_CACHE=off python benchmarks/check_determinism.py
"""

import equinox as eqx
import jax
import numpy as np

import pobax.agent._train as T
from pobax.agent import TrainConfig, train


def main():
    cfg = TrainConfig(env="rocksample_11_11", memory="gru", hidden_size=256, embed_size=96, num_envs=8,
                      num_steps=128, num_minibatches=4, total_steps=8 * 128 * 40, num_seeds=1, num_chunks=4,
                      entropy_coeff=(0.2,))

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
