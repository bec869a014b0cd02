"""The training driver: every (hyperparameter set × seed) run of a configuration in one compiled program.

The device runs a chunk of updates as a `jax.lax.scan`, vmapped over runs; the host only sees chunk
boundaries, where it prints progress and writes the chunk's metrics. A configuration compiles once: the
numeric hyperparameters are array arguments, and the chunk's start is an array too.
"""

import collections
import concurrent.futures
import contextlib
import dataclasses
import datetime
import hashlib
import json
import math
import os
import tempfile
import sys
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from .._paths import cache_dir
from .._version import commit
from ..env import make, spec
from ..eval._results import RunDir, atomic_write_text, write_json
from ..eval._stats import auc, bootstrap_ci, final_value
from ..memory._layers import matmul_batch, split_gemms
from ._config import NUMERIC, Hyperparams, TrainConfig, config_differences, validate
from ._ppo import TrainState, init_state, update

#: Number of times the chunk program was traced (compiled) in this process; tests use it.
TRACE_COUNT = 0


def default_unroll() -> int:
    return 1 if jax.default_backend() == "cpu" else 4


def structural(cfg: TrainConfig) -> TrainConfig:
    """The part of a configuration that shapes the compiled program (numeric values, seeds and logging
    are arguments, not part of the program)."""
    unroll = cfg.unroll if cfg.unroll is not None else default_unroll()
    return dataclasses.replace(cfg, **{k: () for k in NUMERIC}, seed=0, num_seeds=1, num_chunks=1, unroll=unroll)


#: Compile the initialisation on a GPU with JAX's threefry kernel (see `_init_lowering`); False: XLA's inlined hash, as everywhere else.
INIT_THREEFRY_KERNEL = True


#: XLA options for the programs `train` compiles on an NVIDIA GPU; an option that is also in $XLA_FLAGS is left to it.
#: `xla_gpu_experimental_autotune_backends`: XLA's autotuner tries, besides its GEMM and convolution libraries, the
#: Triton block-level emitter against its own for every fusion and cuBLASLt against Triton for every GEMM fusion
#: (`BLOCK_LEVEL_EMITTER`, `CUBLASLT_FISSION`). For RockSample GRU that is 215 of the 426 kernels it compiles and
#: times, and Triton's GEMMs and XLA's emitter won nearly everywhere. Leaving those two out saved RockSample GRU
#: 1.2 s on average (0.3-2.4 s, 8 paired runs) of its 10-15 s cold compile on an H200, T-Maze 0.4-0.6 s, at the same
#: env steps/s (benchmarks/README.md, "Compile time, session 7"). `{}`: XLA's defaults.
GPU_COMPILER_OPTIONS = {"xla_gpu_experimental_autotune_backends": "CUDNN,TRITON,CUBLASLT,NATIVE_EMITTER,CUSTOM_KERNEL"}
_UNKNOWN_OPTIONS: set = set()  # options this jaxlib rejected (an older or newer XLA): not passed again


def _on_nvidia_gpu() -> bool:
    return jax.default_backend() == "gpu" and jax.devices()[0].device_kind.upper().startswith("NVIDIA")


#: On an NVIDIA GPU (TF32-capable), for networks at least this wide (`TrainConfig.hidden_size`), the chunk program's
#: GEMMs are split between XLA's two GEMM backends (`pobax.memory._layers.split_gemms`): the products over whole
#: sequences (the replay's dense layers, the GRU's input projection and weight gradient, forward and backward) go to
#: cuBLAS, the products inside sequential loops (the rollout's steps, the GRU's recurrence) stay Triton's fused GEMMs.
#: XLA's autotuner compiles and times ~8-14 Triton tilings for every distinct GEMM fusion (3-6 s of a cold start at
#: 256-512 wide); cuBLAS serves the sequence products as well, while in the loops Triton's GEMMs are worth 20% of the
#: env steps/s (Battleship). Applies only where every matrix product of the program is one the network placed (not
#: with MuJoCo's physics, convolutions or attention); below the width (T-Maze, 32 wide) Triton's fused GEMMs are
#: faster everywhere. Measured on an H200 (benchmarks/README.md, "Session 11"). None: never. A
#: `--xla_gpu_triton_gemm_any` or `--xla_gpu_enable_triton_gemm` in $XLA_FLAGS turns the rule off.
CUBLAS_MIN_HIDDEN: int | None = 256
#: The chunk's options where the rule applies: `xla_gpu_triton_gemm_any` off sends the products with nothing to fuse
#: (the isolated sequence products) to cuBLAS.
SPLIT_OPTIONS = {"xla_gpu_triton_gemm_any": False}
#: Added where no product is left to Triton (no sequential loop has one: RockSample's rollout and recurrence are
#: multiply-sums): XLA picks each GEMM's cuBLAS algorithm by timing them, and near ties went either way from one
#: process to the next (RockSample GRU, the same seed: 4 different runs in 5 processes on an H200); with it, every
#: process compiles the same program (5 of 5). XLA cannot compile Triton's GEMMs with it ("No supported config"), so a
#: program that keeps some (Battleship) goes without: there the picks were the same in 9 of 9 processes.
DETERMINISTIC_OPTIONS = {"xla_gpu_deterministic_ops": True}


def gemm_split(cfg: TrainConfig, runs: int) -> bool:
    """Whether the chunk program of `cfg` with `runs` vmapped runs is traced with `split_gemms` (see
    `CUBLAS_MIN_HIDDEN`)."""
    flags = os.environ.get("XLA_FLAGS", "")
    return (CUBLAS_MIN_HIDDEN is not None and cfg.hidden_size >= CUBLAS_MIN_HIDDEN and runs == 1 and _tf32_gpu()
            and "--xla_gpu_triton_gemm_any" not in flags and "--xla_gpu_enable_triton_gemm" not in flags)


def _tf32_gpu() -> bool:
    """An NVIDIA GPU with TF32 (compute capability 8.0 or later)."""
    return _on_nvidia_gpu() and float(getattr(jax.devices()[0], "compute_capability", "0")) >= 8.0


#: On an NVIDIA GPU (TF32-capable, where it was measured), one run of a narrow network (`TrainConfig.hidden_size` at
#: most this) whose every matrix product is the network's: the chunk program's GEMMs all get one Triton tiling,
#: `GEMM_TILING`, instead of XLA's autotuning, which compiles and times ~6 tilings for each distinct GEMM fusion (T-Maze
#: GRU 1 seed: 82 kernels for 14 GEMMs). At these sizes a product is a few tiles, and the tiling XLA's autotuner picked
#: most often for them trains as fast: measured on an H200 (benchmarks/README.md, "Session 12"). Nothing is timed, so
#: every process compiles the same program. Several runs keep the autotuner (the one tiling cost them 1.4-3.2% of
#: their env steps/s), and so do wider networks (Battleship lost 11% with one tiling per GEMM picked by XLA's cost
#: model). None: never. A `--xla_gpu_gemm_autotuner_override_file` in $XLA_FLAGS turns the rule off.
TILING_MAX_HIDDEN: int | None = 64
#: The tiling (XLA's `TritonGemmConfigsProto` as text): 64 × 32 output tiles, 32 deep, one stage, 4 warps.
GEMM_TILING = "config { block_m: 64 block_n: 32 block_k: 32 num_stages: 1 num_warps: 4 num_ctas: 1 }\n"
#: The XLA option that takes it: the path of a file that lists Triton's tilings for every GEMM fusion.
TILING_OPTION = "xla_gpu_gemm_autotuner_override_file"


def gemm_tiling(cfg: TrainConfig, runs: int) -> bool:
    """Whether the chunk program of `cfg` with `runs` runs may get `GEMM_TILING` (see `TILING_MAX_HIDDEN`)."""
    return TILING_MAX_HIDDEN is not None and cfg.hidden_size <= TILING_MAX_HIDDEN and runs == 1 and _tf32_gpu()


def _tiling_file() -> str | None:
    """`GEMM_TILING` in a file named by its content (XLA reads the option as a path, and the persistent compilation
    cache keys on the path), in pobax's cache directory or else the temporary one; None if neither is writable."""
    name = f"triton-tiling-{hashlib.sha256(GEMM_TILING.encode()).hexdigest()[:16]}.textproto"
    for path in (cache_dir() / name, Path(tempfile.gettempdir()) / name):
        try:
            if not path.is_file() or path.read_text() != GEMM_TILING:
                atomic_write_text(path, GEMM_TILING)  # whole or absent, with other processes writing it too
            return str(path)
        except OSError:
            continue
    return None


def _products(jaxpr) -> set:
    """The kinds of matrix products in `jaxpr` (a Jaxpr or ClosedJaxpr), nested jaxprs (loops, branches, calls)
    included: "tf32" and "default" (the network's: the TF32 algorithm that `split_gemms` gives the loops' products,
    DEFAULT precision spelled out everywhere else) and "unplaced" (any other precision or none, or a convolution)."""
    kinds = set()
    for eqn in getattr(jaxpr, "jaxpr", jaxpr).eqns:  # a ClosedJaxpr's Jaxpr
        if eqn.primitive.name == "conv_general_dilated":
            kinds.add("unplaced")
        elif eqn.primitive.name == "dot_general":
            precision = eqn.params.get("precision")
            default = jax.lax.Precision.DEFAULT
            kinds.add("tf32" if precision == jax.lax.DotAlgorithmPreset.TF32_TF32_F32 else
                      "default" if precision == (default, default) else "unplaced")
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                if hasattr(getattr(sub, "jaxpr", sub), "eqns"):
                    kinds |= _products(sub)
    return kinds


def chunk_options(cfg: TrainConfig, runs: int, jaxpr) -> dict:
    """XLA options for the chunk program of `cfg` with `runs` vmapped runs (traced to `jaxpr`) beyond
    `compiler_options()`, where every product of the program is the network's: `SPLIT_OPTIONS` (and
    `DETERMINISTIC_OPTIONS` where no loop has a product) where the rule of `CUBLAS_MIN_HIDDEN` applies, `GEMM_TILING`
    where that of `TILING_MAX_HIDDEN` does."""
    split, tiling = gemm_split(cfg, runs), gemm_tiling(cfg, runs)
    if not (split or tiling):
        return {}
    kinds = _products(jaxpr)
    if "unplaced" in kinds:
        return {}
    if split:
        return {**SPLIT_OPTIONS, **({} if "tf32" in kinds else DETERMINISTIC_OPTIONS)}
    path = _tiling_file()
    return {TILING_OPTION: path} if path else {}


def compiler_options(extra: dict | None = None) -> dict:
    """The XLA options `train` compiles a program with here: `GPU_COMPILER_OPTIONS` on an NVIDIA GPU and the
    program's own `extra`, less those set in $XLA_FLAGS (the user's) and those this XLA rejected."""
    options = {**(GPU_COMPILER_OPTIONS if _on_nvidia_gpu() else {}), **(extra or {})}
    flags = os.environ.get("XLA_FLAGS", "")
    return {k: v for k, v in options.items() if f"--{k}" not in flags and k not in _UNKNOWN_OPTIONS}


def _compile(lowered, extra: dict | None = None):
    """`lowered.compile()` with `compiler_options(extra)`; an option this XLA does not know is dropped with a
    warning."""
    options = compiler_options(extra)
    try:
        return lowered.compile(compiler_options=options) if options else lowered.compile()
    except jax.errors.JaxRuntimeError as e:
        drop, then = (), ""
        if DETERMINISTIC_OPTIONS.keys() & options.keys() and "No supported config" in str(e):
            # XLA finds no Triton tiling it can compile with deterministic ops
            drop, then = DETERMINISTIC_OPTIONS.keys(), "the same seed may train another run in another process"
        elif "compile option" not in str(e) and TILING_OPTION in options:
            # e.g. a Triton that cannot build the tiling, or an XLA that reads the file another way
            drop, then = (TILING_OPTION,), "XLA autotunes the GEMMs instead"
        if drop:
            warnings.warn(f"XLA could not compile this program with {sorted(drop)} ({str(e)[:300]}); compiling "
                          f"without: {then}.", stacklevel=3)
            return _compile(lowered, {k: v for k, v in extra.items() if k not in drop})
        if "compile option" not in str(e):
            raise
        _UNKNOWN_OPTIONS.update(options)
        warnings.warn(f"This XLA rejects the compile options {sorted(options)} ({e}); compiling without them "
                      f"(set pobax.agent._train.GPU_COMPILER_OPTIONS = {{}} to silence this).", stacklevel=3)
        return lowered.compile()


def _is_dynamic(x) -> bool:
    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def _partition(tree):
    """(static, arrays): the arrays (or abstract arrays) of `tree`, and the rest — its structure and other leaves,
    hashable — that `_combine` puts them back into."""
    leaves, treedef = jax.tree.flatten(tree)
    is_dyn = [_is_dynamic(x) for x in leaves]
    return (treedef, tuple(None if d else x for x, d in zip(leaves, is_dyn))), [x for x, d in zip(leaves, is_dyn) if d]


def _combine(static, dynamic):
    treedef, leaves = static
    it = iter(dynamic)
    return jax.tree.unflatten(treedef, [next(it) if x is None else x for x in leaves])


class _Static(eqx.Module):
    """A program output that is not an array (module structure, Python numbers): carried in the output's tree."""

    value: object = eqx.field(static=True)


#: Executables kept per program for reuse in this process (each holds device code and memory).
KEEP_COMPILED = 8
_PROGRAMS: list = []


def clear_compiled() -> None:
    """Drop every compiled program of this process: the executables `train` keeps and JAX's own caches
    (`jax.clear_caches()`). The next call traces and compiles afresh, so module-level switches read when tracing
    (e.g. `pobax.memory._gru.RECURRENT_IMPL`) take effect, and with the persistent compilation cache on it loads
    from that cache as a new process would."""
    for program in _PROGRAMS:
        program._compiled.clear()
    jax.clear_caches()


class _Program:
    """`fn` compiled as one XLA program whose arguments are the arrays in `fn`'s arguments; everything else
    (configuration, environment constants, sizes) is part of the program, as with `eqx.filter_jit`.

    Unlike `eqx.filter_jit` it also compiles from abstract arrays (`jax.ShapeDtypeStruct`), before any argument
    exists, so that `train` lowers its two programs one after the other and compiles them at the same time
    (XLA releases the GIL). `lowering(args)` gives the context (e.g. JAX configuration) to lower `fn(*args)` in.
    Compiled executables are kept per (static part, argument shapes) for the process. `donate`: the position of
    the argument whose arrays the call donates (XLA may write the outputs into their buffers; the caller must not
    use them afterwards), or None. `options(args, jaxpr)`: XLA options of this program beyond `compiler_options()`,
    from its arguments and traced jaxpr.
    """

    def __init__(self, fn, lowering=lambda args: contextlib.nullcontext(), donate: int | None = None, options=None):
        def run(static, *dynamic):
            out_static, out_dynamic = _partition(fn(*_combine(static, dynamic)))
            return out_dynamic, _Static(out_static)

        run.__name__ = run.__qualname__ = fn.__name__
        self._run = run
        self._jits: dict = {}  # per donated positions of `run`'s arguments
        self._donate = donate
        self._lowering = lowering
        self._options = options
        self._compiled: collections.OrderedDict = collections.OrderedDict()
        _PROGRAMS.append(self)

    def _jit(self, args):
        """The jitted `run` for `args`, donating the arrays of `args[self._donate]` (their positions among `run`'s
        arguments depend on the arrays before them)."""
        donated = ()
        if self._donate is not None:
            before = len(_partition(args[: self._donate])[1])
            donated = tuple(range(1 + before, 1 + before + len(_partition(args[self._donate])[1])))
        if donated not in self._jits:
            self._jits[donated] = jax.jit(self._run, static_argnums=0, donate_argnums=donated)
        return self._jits[donated]

    @staticmethod
    def _key(static, dynamic):
        def placement(x):  # only a placement over several devices changes the program
            sharding = getattr(x, "sharding", None)
            return sharding if sharding is not None and len(sharding.device_set) > 1 else None

        return static, tuple((tuple(x.shape), str(x.dtype), placement(x)) for x in dynamic)

    def lower(self, *args):
        """Trace and lower for `args` (arrays or `jax.ShapeDtypeStruct`s). Returns (key, lowered), lowered None
        when this process already compiled it, else (`jax.stages.Lowered`, its XLA options)."""
        static, dynamic = _partition(args)
        key = self._key(static, dynamic)
        if key in self._compiled:
            return key, None
        with self._lowering(args):
            traced = self._jit(args).trace(static, *dynamic)
            return key, (traced.lower(), self._options(args, traced.jaxpr) if self._options else {})

    def compile(self, key, lowered) -> None:
        if lowered is not None:
            self._compiled[key] = _compile(*lowered)
            while len(self._compiled) > KEEP_COMPILED:  # the least recently used executables go
                self._compiled.popitem(last=False)

    def out_shapes(self, key, lowered=None):
        """The abstract output of the call of `key` (arrays as `jax.ShapeDtypeStruct`s), from its lowering or,
        once compiled, from the executable."""
        dynamic, static = (lowered[0] if lowered is not None else self._compiled[key]).out_info
        return _combine(static.value, dynamic)

    def __call__(self, *args):
        static, dynamic = _partition(args)
        key = self._key(static, dynamic)
        if key not in self._compiled:
            self.compile(*self.lower(*args))
        self._compiled.move_to_end(key)
        dyn_out, static_out = self._compiled[key](*dynamic)
        return _combine(static_out.value, dyn_out)


def run_layout(cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """How `train` orders the runs of `cfg`: run i trains the set `hp_index[i]` of `cfg.grid()` with the seed index
    `seed_index[i]`, each set's seeds next to each other."""
    n_sets = len(cfg.grid())
    return np.repeat(np.arange(n_sets), cfg.num_seeds), np.tile(np.arange(cfg.num_seeds), n_sets)


def run_hyperparams(cfg: TrainConfig) -> Hyperparams:
    """The numeric hyperparameters of `cfg`'s runs, stacked in `run_layout`'s order."""
    grid = cfg.grid()
    return Hyperparams.stack([grid[h] for h in run_layout(cfg)[0]])


#: One run's programs (initialisation and chunk) are traced without the `vmap` over runs (the run axis is taken off
#: and put back): the same computation (float rounding aside: XLA fuses it a little differently), without a batch
#: dimension of 1 on every operation. Measured: Battleship GRU 1 seed trains at 100.0-100.5k env steps/s against
#: 97.8-98.0k on an H200, other 1-seed cases alike; T-Maze's chunk compiles ~0.5 s faster on a 2-core CPU
#: (benchmarks/README.md, "Session 12").
SINGLE_RUN_UNBATCHED = True


def _map_runs(fn, *args):
    """`fn` over the leading run axis of `args`: `jax.vmap`, or for one run `fn` of that run with the axis put back
    (`SINGLE_RUN_UNBATCHED`)."""
    if _runs(args) == 1 and SINGLE_RUN_UNBATCHED:
        return jax.tree.map(lambda x: x[None], fn(*jax.tree.map(lambda x: x[0], args)))
    return jax.vmap(fn)(*args)


def _init_runs(cfg: TrainConfig, env, seed, run_seed, num_seeds: int, threefry_kernel: bool) -> TrainState:
    # Seed s uses the same key in every hyperparameter set: common random numbers make sets comparable.
    # (`seed` is the base seed as uint32: the same keys as `jax.random.key(cfg.seed)` on the host.)
    keys = jax.random.split(jax.random.key(seed), num_seeds)[run_seed]
    return _map_runs(lambda k: init_state(cfg, env, k), keys)


@contextlib.contextmanager
def _init_lowering(args):
    """The initialisation program is lowered, on a GPU, with JAX's hand-written threefry kernel
    (`jax_threefry_gpu_kernel_lowering`; its last argument says so): the same random bits, but every random draw
    of the network's initialisation is one kernel call instead of XLA's inlined hash, which XLA's fusion pass is
    slow on — measured, it saves 1.6-2.5 s of compile time per run on an H200 (benchmarks/README.md, "Compile
    time"). It runs once, so the fusion the inlined hash would allow is worth nothing here; the training program
    keeps XLA's lowering, which fuses into the rollout."""
    if not args[-1]:
        yield
        return
    before = jax.config.jax_threefry_gpu_kernel_lowering
    jax.config.update("jax_threefry_gpu_kernel_lowering", True)
    try:
        yield
    finally:
        jax.config.update("jax_threefry_gpu_kernel_lowering", before)


_INIT = _Program(_init_runs, lowering=_init_lowering)


def _init_args(cfg: TrainConfig, env, run_seed) -> tuple:
    """The arguments of the initialisation program for the runs of `cfg` (`run_seed[i]`: run i's seed index)."""
    kernel = jax.default_backend() == "gpu" and INIT_THREEFRY_KERNEL
    seed = np.asarray(cfg.seed % 2**32, np.uint32)
    return (structural(cfg), env, seed, run_seed, cfg.num_seeds, kernel)


def _init(cfg: TrainConfig, env, run_seed) -> TrainState:
    """The initial states of the runs (`run_seed[i]`: the seed index of run i; `cfg.seed`: the base seed)."""
    return _INIT(*_init_args(cfg, env, np.asarray(run_seed, np.int32)))


def chunk_length(cfg: TrainConfig) -> int:
    """Updates per compiled chunk: the run's updates split into at most `num_chunks` equal chunks (the last one
    padded)."""
    return math.ceil(cfg.num_updates / min(cfg.num_chunks, cfg.num_updates))


def _chunk_runs(cfg: TrainConfig, env, state: TrainState, hp: Hyperparams, start, chunk_len: int):
    global TRACE_COUNT
    TRACE_COUNT += 1

    def one_run(state, hp):
        # The update is traced once: its jaxpr gives both the branch that runs and the shapes of the metrics
        # that the padding branch returns as zeros (`jax.eval_shape` would trace it a second time).
        step = eqx.filter_closure_convert(lambda s: update(cfg, env, s, hp), state)
        zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), step.out_struct[1])

        def body(state, i):
            # `start` is not batched, so this stays a real branch under vmap: the padding updates of the last
            # chunk cost nothing. (Replacing it by computing and discarding them was measured: no faster on an
            # H200, 511k vs 518-526k env steps/s for T-Maze GRU × 30 seeds.)
            return jax.lax.cond(start + i < cfg.num_updates, lambda s: step(s), lambda s: (s, zeros), state)

        return jax.lax.scan(body, state, jnp.arange(chunk_len))

    # The rollout calls the network on one step of each environment of each run (see `matmul_t`).
    with matmul_batch(_runs(state) * cfg.num_envs):
        return _map_runs(one_run, state, hp)


#: The chunk donates the training state it is given (argument 2): the state it returns takes its buffers, so a run
#: holds one copy of its state on the device, not two.
_CHUNK = _Program(_chunk_runs, lowering=lambda args: split_gemms(gemm_split(args[0], _runs(args[2]))), donate=2,
                  options=lambda args, jaxpr: chunk_options(args[0], _runs(args[2]), jaxpr))


def _runs(state) -> int:
    return jax.tree.leaves(state)[0].shape[0]


def _chunk(cfg: TrainConfig, env, state: TrainState, hp: Hyperparams, start, chunk_len: int):
    """`chunk_len` updates of every run from update `start` (updates past `cfg.num_updates` are skipped)."""
    return _CHUNK(cfg, env, state, hp, np.asarray(start, np.int32), chunk_len)


#: Compile the initialisation and chunk programs at the same time: None (default) on accelerators only, True, False.
#: (On a CPU, XLA already compiles with every core.)
PARALLEL_COMPILE = None


def _compile_programs(init_args: tuple, hp, chunk_len: int, sharding=None) -> None:
    """Compile the initialisation and the chunk programs of a run, at the same time on accelerators.

    Both are traced and lowered here, one after the other (Python); XLA then compiles them in two threads — the
    chunk program's shapes come from the initialisation's lowered output, so it need not run first."""
    scfg, env = init_args[:2]
    init_key, init_low = _INIT.lower(*init_args)
    state = _INIT.out_shapes(init_key, init_low)
    if sharding is not None:
        state = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), state)
    parallel = PARALLEL_COMPILE if PARALLEL_COMPILE is not None else jax.default_backend() != "cpu"
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pending = pool.submit(_INIT.compile, init_key, init_low) if parallel else None
        if pending is None:
            _INIT.compile(init_key, init_low)
        _CHUNK.compile(*_CHUNK.lower(scfg, env, state, hp, jax.ShapeDtypeStruct((), jnp.int32), chunk_len))
        if pending is not None:
            pending.result()


@dataclasses.dataclass
class TrainResult:
    """What `train` returns: the final state of every run, the metrics table and the summary. `compile_s`: what
    starting cost beyond steady training — compiling both programs and running the initialisation, plus the first
    chunk's time beyond a steady chunk's — i.e. compilation, nearly all of it."""

    config: TrainConfig
    state: TrainState
    metrics: pd.DataFrame
    summary: dict
    run_dir: Path | None
    compile_s: float
    steps_per_s: float


def default_out(cfg: TrainConfig) -> Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    agent = cfg.memory + ("-ld" if cfg.double_critic else "")
    return Path("runs") / f"{cfg.env}-{cfg.observability}-{agent}-{stamp}"


class _Progress:
    def __init__(self, enabled: bool, total: int):
        self.enabled, self.total = enabled, total
        self.tty = sys.stderr.isatty()

    def __call__(self, done_steps: int, sps: float, ret: float, disc: float, chunk: int, n_chunks: int):
        if not self.enabled:
            return
        msg = (f"[{chunk}/{n_chunks}] {done_steps:,}/{self.total:,} steps per run | {sps:,.0f} env steps/s | "
               f"return {ret:.3f} (discounted {disc:.3f})")
        print(("\r" + msg) if self.tty else msg, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self):
        if self.enabled and self.tty:
            print(file=sys.stderr)


def summarize(cfg: TrainConfig, metrics: pd.DataFrame) -> dict:
    """Per hyperparameter set, discounted and undiscounted: final returns (mean over the last 10% of updates per
    seed) and the area under the learning curve (`auc`), each as mean and 95% bootstrap CI over seeds. The
    best set by AUC of the discounted return (the paper's selection criterion) is `best_by_auc`."""
    sets = []
    for h, hp in enumerate(cfg.grid()):
        df = metrics[metrics.hp_index == h]
        row = {"hp_index": h, **hp}
        for col in ("return", "disc_return"):
            curves = [g.sort_values("update")[col].to_numpy() for _, g in df.groupby("seed")]
            finals = [final_value(c) for c in curves]
            mean, lo, hi = bootstrap_ci(finals)
            row[col] = {"mean": mean, "ci_low": lo, "ci_high": hi, "per_seed": finals}
            aucs = [auc(c) for c in curves]
            mean, lo, hi = bootstrap_ci(aucs)
            row[f"{col}_auc"] = {"mean": mean, "ci_low": lo, "ci_high": hi, "per_seed": aucs}
        sets.append(row)
    best = max(range(len(sets)), key=lambda i: -np.inf if np.isnan(sets[i]["disc_return_auc"]["mean"])
               else sets[i]["disc_return_auc"]["mean"])
    return {"env": cfg.env, "observability": cfg.observability, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "num_seeds": cfg.num_seeds, "final_fraction": 0.1,
            "best_by_auc": best, "sets": sets}


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed (missing, corrupted, or from another configuration)."""


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _to_storable(state):
    # typed PRNG keys are stored as their raw key data
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, state)


def _save_checkpoint(run_dir: RunDir, state: TrainState, chunk: int, n_chunks: int) -> None:
    """The full training state of every run after `chunk` (parameters, optimiser state, environment states,
    memory carries, observation statistics, keys, episode statistics) and the logger's position."""
    fd, tmp = tempfile.mkstemp(dir=run_dir.path, prefix=".checkpoint.", suffix=".tmp")
    os.close(fd)
    try:
        eqx.tree_serialise_leaves(tmp, _to_storable(jax.device_get(state)))
        os.replace(tmp, run_dir.path / "checkpoint.eqx")
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    write_json(run_dir.path / "checkpoint.json", {"chunks_done": chunk + 1, "num_chunks": n_chunks})


def _load_checkpoint(run_dir: RunDir, like: TrainState) -> tuple[TrainState, int]:
    path = run_dir.path / "checkpoint.eqx"
    meta = run_dir.path / "checkpoint.json"
    if not path.exists() or not meta.exists():
        raise CheckpointError(
            f"No checkpoint in {str(run_dir.path)!r} (expected checkpoint.eqx and checkpoint.json): it was not "
            f"written by `train`, or the run finished (see summary.json)."
        )
    done = int(json.loads(meta.read_text())["chunks_done"])
    try:
        stored = eqx.tree_deserialise_leaves(path, _to_storable(like))
    except Exception as e:  # noqa: BLE001  (truncated file, wrong shapes)
        raise CheckpointError(f"Checkpoint {str(path)!r} is corrupted or does not match this run ({e}).") from None
    restored = jax.tree.map(
        lambda x, ref: jax.random.wrap_key_data(x, impl=jax.random.key_impl(ref)) if _is_key(ref) else x,
        stored, like,
    )
    return restored, done


def train(
    cfg: TrainConfig,
    out: str | Path | None = None,
    *,
    save: bool = True,
    progress: bool = True,
    resume: bool = False,
    max_chunks: int | None = None,
    devices: list | None = None,
    loggers: tuple[str, ...] = (),
) -> TrainResult:
    """Train every hyperparameter set × seed of `cfg` together. Writes a run directory unless `save=False`.

    The run directory gets a checkpoint of the whole training state at every chunk boundary. `resume=True`
    continues the interrupted run in `out` (which must hold the same configuration) from its last checkpoint,
    and produces the same metrics, bit for bit, as an uninterrupted run. `max_chunks` stops after that many
    chunks in this call, leaving a resumable run (the returned summary covers the chunks done so far).
    `loggers` ("tensorboard", "wandb") also send every chunk's metrics to those trackers, one logical run per
    (hyperparameter set, seed). `devices` (default: all local devices) are the devices the runs are sharded over; across machines, start
    every process with `jax.distributed.initialize()` and pass `jax.devices()` (see the README).
    """
    validate(cfg)
    from ..eval._loggers import check_available, make_loggers  # noqa: PLC0415

    check_available(loggers)
    if resume and (out is None or not save):
        raise CheckpointError("resume needs the run directory to continue: pass it as `out` (--out / --resume).")
    env = make(cfg.env, cfg.observability, action_concat=cfg.action_concat)
    grid = cfg.grid()
    hp_index, seed_index = run_layout(cfg)
    # Runs are sharded over `devices` (default: every local accelerator); the batch is padded with copies of
    # the last run to a multiple of the device count, and the copies are dropped from the results.
    devs = jax.local_devices() if devices is None else list(devices)
    n_runs = len(hp_index)
    pad = (-n_runs) % len(devs)
    run_hp = np.concatenate([hp_index, np.repeat(hp_index[-1:], pad)])
    run_seed = np.concatenate([seed_index, np.repeat(seed_index[-1:], pad)]).astype(np.int32)
    hp = Hyperparams.stack([grid[h] for h in run_hp])
    sharding = None
    if len(devs) > 1:
        sharding = jax.sharding.NamedSharding(jax.sharding.Mesh(np.array(devs), ("runs",)),
                                              jax.sharding.PartitionSpec("runs"))
        hp, run_seed = jax.device_put((hp, run_seed), sharding)

    run_dir = None
    if resume:
        run_dir = RunDir(out)
        if not (run_dir.path / "config.json").exists():
            raise CheckpointError(f"{str(run_dir.path)!r} is not a run directory (no config.json): nothing to resume.")
        diff = config_differences(run_dir.read_config().get("config", {}), cfg)
        if diff:
            raise CheckpointError(
                f"The run in {str(run_dir.path)!r} has another configuration (differs in: {', '.join(diff)}); "
                f"resume it with its own configuration, or start a new run with another --out."
            )
        if (run_dir.path / "summary.json").exists() and not (run_dir.path / "checkpoint.json").exists():
            raise CheckpointError(f"The run in {str(run_dir.path)!r} already finished (summary.json): nothing to resume.")
    elif save:
        run_dir = RunDir.create(out if out is not None else default_out(cfg))
        run_dir.write_config({
            "config": dataclasses.asdict(cfg),
            "hyperparameter_sets": grid,
            "env_spec": {"categories": spec(cfg.env).categories, "gamma": env.gamma,
                         "reference": spec(cfg.env).reference(cfg.observability)},
            "jax": jax.__version__, "device": str(jax.devices()[0].device_kind), "pobax_commit": commit(),
        })

    trackers = make_loggers(loggers, run_dir.path if run_dir is not None else None, dataclasses.asdict(cfg))
    scfg = structural(cfg)
    num_updates = cfg.num_updates
    chunk_len = chunk_length(cfg)
    t_init = time.perf_counter()
    init_args = _init_args(cfg, env, run_seed)
    _compile_programs(init_args, hp, chunk_len, sharding)
    state = jax.block_until_ready(_INIT(*init_args))
    if sharding is not None:
        state = jax.device_put(state, sharding)
    init_s = time.perf_counter() - t_init
    n_chunks = math.ceil(num_updates / chunk_len)
    steps_per_update = cfg.steps_per_update
    show = _Progress(progress, num_updates * steps_per_update)
    frames, chunk_times = [], []
    first = 0
    if resume:
        state, first = _load_checkpoint(run_dir, state)
        frames = [pd.read_csv(run_dir.path / "metrics" / f"{c:05d}.csv") for c in range(first)]
    last = n_chunks if max_chunks is None else min(n_chunks, first + max_chunks)
    for c in range(first, last):
        start = c * chunk_len
        t0 = time.perf_counter()
        state, m = _chunk(scfg, env, state, hp, start, chunk_len)
        m = {k: v[:n_runs] for k, v in jax.device_get(m).items()}
        dt = time.perf_counter() - t0
        chunk_times.append(dt)
        n_valid = min(chunk_len, num_updates - start)
        df = _chunk_frame(m, n_valid, start, steps_per_update, hp_index, seed_index, grid)
        # Throughput of the chunk (all runs together; the first chunk includes compilation).
        df["steps_per_s"] = n_runs * n_valid * steps_per_update / dt
        frames.append(df)
        for t in trackers:
            t.log(df)
        if run_dir is not None:
            run_dir.write_chunk(c, df)
            if c + 1 < n_chunks:
                _save_checkpoint(run_dir, state, c, n_chunks)
        show((start + n_valid) * steps_per_update, n_runs * n_valid * steps_per_update / dt,
             float(np.nanmean(df["return"])) if df["return"].notna().any() else float("nan"),
             float(np.nanmean(df["disc_return"])) if df["disc_return"].notna().any() else float("nan"),
             c + 1, n_chunks)
    show.close()
    for t in trackers:
        t.close()

    metrics = pd.concat(frames, ignore_index=True)
    if pad:
        state = jax.tree.map(lambda x: x[:n_runs], state)
    if chunk_times:
        steady = chunk_times[1:] if len(chunk_times) > 1 else chunk_times
        per_update = float(np.median([t / chunk_len for t in steady]))
        # everything the first chunk cost beyond a steady one, plus the initialisation (nearly all compilation)
        compile_s = init_s + max(0.0, chunk_times[0] - per_update * chunk_len) if len(chunk_times) > 1 else float("nan")
        sps = n_runs * steps_per_update / per_update
    else:
        compile_s = sps = float("nan")
    summary = summarize(cfg, metrics)
    finished = last == n_chunks
    summary.update(compile_s=compile_s, steps_per_s=sps, wall_s=float(sum(chunk_times)), finished=finished)
    if run_dir is not None and finished:
        run_dir.write_metrics(metrics)
        run_dir.save_model(state.model)
        run_dir.write_summary(summary)
        for name in ("checkpoint.eqx", "checkpoint.json"):  # the run is complete: its results are the files above
            (run_dir.path / name).unlink(missing_ok=True)
    return TrainResult(cfg, state, metrics, summary, run_dir.path if run_dir else None, compile_s, sps)


def _chunk_frame(m: dict, n_valid: int, start: int, steps_per_update: int, hp_index, seed_index, grid) -> pd.DataFrame:
    runs = len(hp_index)
    upd = np.arange(start, start + n_valid)
    cols = {
        "hp_index": np.repeat(hp_index, n_valid),
        "seed": np.repeat(seed_index, n_valid),
        "update": np.tile(upd, runs),
        "env_step": np.tile((upd + 1) * steps_per_update, runs),
    }
    for k in NUMERIC:
        cols[k] = np.repeat([grid[h][k] for h in hp_index], n_valid)
    m = {k: np.asarray(v)[:, :n_valid].reshape(-1) for k, v in m.items()}
    episodes = m.pop("episodes")
    with np.errstate(invalid="ignore", divide="ignore"):
        cols["return"] = np.where(episodes > 0, m.pop("return_sum") / episodes, np.nan)
        cols["disc_return"] = np.where(episodes > 0, m.pop("disc_return_sum") / episodes, np.nan)
        cols["ep_length"] = np.where(episodes > 0, m.pop("length_sum") / episodes, np.nan)
        for k in [k for k in m if k.startswith("episode/")]:  # per-episode info (env.episode_metrics): mean
            cols[k.removeprefix("episode/")] = np.where(episodes > 0, m.pop(k) / episodes, np.nan)
    cols["episodes"] = episodes
    cols["lr_now"] = m.pop("lr")
    cols.update(m)
    # float64 throughout: a chunk read back from its CSV file is then identical to the one in memory (resume)
    return pd.DataFrame({k: np.asarray(v, np.float64) if np.asarray(v).dtype.kind == "f" else v
                         for k, v in cols.items()})
