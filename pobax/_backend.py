"""Every choice pobax makes by backend (GPU, CPU, other accelerators) is here; nothing else asks which it is on.

Each choice picks the faster of two computations of the same function (tested to agree up to float rounding), or
avoids a known failure; the measurements behind them are in docs/performance.md. Modules take the choice as a
constructor or function argument whose default ("auto") defers to the function here, so a test can ask for either
computation on any backend.
"""

import jax


def platform() -> str:
    """"cpu", "gpu" or another JAX backend name."""
    return jax.default_backend()


def default_unroll() -> int:
    """Unroll factor of the GRU's replay loops: 4 on accelerators (fewer, larger kernels: RockSample GRU 1 seed
    21.8k → 34.2k env steps/s on an H200), 1 on the CPU."""
    return 1 if platform() == "cpu" else 4


def gru_impl(hidden_size: int) -> str:
    """How the GRU runs its time loop (`pobax.memory.GRU`'s `impl`): on GPUs the fused Pallas kernel up to 64 wide
    (T-Maze GRU × 30 seeds 1.76M vs 526k env steps/s), else the scan with the recurrent product as a multiply-sum up
    to 256 wide on accelerators (RockSample 29.2k vs 23.5k), else the scan with a matrix product (Battleship, CPUs)."""
    if platform() == "gpu" and hidden_size <= 64:
        return "fused"
    return recurrent_product(hidden_size)


def lstm_impl(hidden_size: int) -> str:
    """How the LSTM runs its time loop (`pobax.memory.LSTM`'s `impl`): on GPUs the fused Pallas kernels up to 32
    wide (T-Maze's width; docs/performance.md), else the scan with the recurrent product `recurrent_product` picks."""
    if platform() == "gpu" and hidden_size <= 32:
        return "fused"
    return recurrent_product(hidden_size, gates=4)


def recurrent_product(hidden_size: int, gates: int = 3) -> str:
    """How a recurrent cell's scan computes `weight_hh @ h` (the GRU's and LSTM's `impl`/`product`), for a
    `(gates × hidden, hidden)` weight: as a multiply-sum that XLA fuses with the gate arithmetic ("reduce") on
    accelerators up to the GRU's 3 × 256² entries, else a matrix product ("dot"). The bound is where the multiply-sum
    was measured: faster for the GRU at 256 wide (RockSample 1 seed 29.2k vs 23.5k env steps/s); the LSTM at 256
    (4 × 256²), RockSample 11 × 120 runs, finished no chunk in 25 min after XLA's "very slow compile" warning, while
    "dot" compiled in 34 s and ran 1.49M env steps/s (H200, 2026-11-27, docs/performance.md)."""
    return "reduce" if platform() != "cpu" and gates * hidden_size**2 <= 3 * 256**2 else "dot"


def rollout_reduce_limit() -> int:
    """Largest rows × weight entries for which a dense layer on one time step is a multiply-sum instead of a matrix
    product (`pobax.memory.matmul_t`): 2**22 on accelerators (T-Maze GRU 1 seed +20%, RockSample +3-4%; unbounded,
    Battleship lost 5%), 0 on the CPU, where the matrix product is faster."""
    return 0 if platform() == "cpu" else 2**22


def orthogonal_method() -> str:
    """How `pobax.memory.orthogonal` orthonormalises: a QR decomposition on GPUs (one cuSOLVER call), Gram–Schmidt
    elsewhere (jaxlib's CPU LAPACK QR can deadlock when several batched QRs run at once on a small machine)."""
    return "qr" if platform() == "gpu" else "gram_schmidt"


def reset_pool_size() -> int | None:
    """`AutoReset.pool_size` for environments whose reset costs about a step or more (RockSample, Battleship): 8 done
    environments reset per round on the CPU (RockSample 11 env-only at 64 envs 0.63-1.18M → 2.44-2.49M steps/s on 2
    cores), a reset computed for every environment on accelerators (the pool's `while_loop` would synchronise with
    the host every step)."""
    return 8 if platform() == "cpu" else None


def loop_free_placements() -> bool:
    """Battleship resets draw ship placements in a fixed number of rounds (no `while_loop`) on accelerators, where
    the loop synchronises with the host every step (training Battleship GRU 96.2k → 101.3k env steps/s on an H200);
    the CPU keeps the loop (no synchronisation to save, less to compile)."""
    return platform() != "cpu"


def compiler_options(deterministic: bool = False, fast_compile: bool = False) -> dict:
    """XLA options of the training programs. `deterministic` on a GPU: XLA's deterministic ops and no autotuning by
    timing, so that the same seed trains the same run in every process on the same kind of GPU (XLA otherwise picks
    each GEMM's kernel by timing candidates, and near ties go either way from one process to the next).
    `fast_compile`: LLVM's optimisations off (T-Maze GRU, hidden 16: both programs compile in 4.0 s instead of 13.8 s
    on 2 CPU cores)."""
    options = {}
    if deterministic and platform() == "gpu":
        options.update(xla_gpu_deterministic_ops=True, xla_gpu_autotune_level=0)
    if fast_compile:
        options.update(xla_backend_optimization_level=0, xla_llvm_disable_expensive_passes=True)
    return options
