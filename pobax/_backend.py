"""The one module that maps a platform ("cpu", "gpu", ...) to pobax's implementation choices.

Each choice picks the faster of two computations of the same function (tested to agree up to float rounding), or
avoids a known failure. Nothing here asks JAX which platform it is on while a program is traced: the training entry
point (`pobax.agent.Runs`) resolves a `Backend` once from the devices it will run on (`Backend.of(devices)`) and
passes it down as arguments and module fields (`GRU(platform=...)`, `AutoReset(pool_size=...)`, ...). Modules built
without one take the CPU's choices, which run on every platform; `pobax.memory.orthogonal`, which every layer's
initialiser calls (a user's cell's too), chooses when its program is lowered for its devices
(`by_lowering_platform`). Compare the choices on a device with
`python benchmarks/bench_train.py --cases CASE --backend default NAME=VALUE` (NAME: `OVERRIDES`) or
`python benchmarks/bench_env.py --envs ENV --backend NAME=VALUE`; docs/performance.md has the figures.
"""

import dataclasses

import jax


def platform_of(devices=None) -> str:
    """The platform of `devices` (default: JAX's default devices), as `jax.Device.platform` names it: "cpu", "gpu",
    "tpu", ... Raises ValueError for devices of several platforms (one program runs on one)."""
    platforms = {d.platform for d in (jax.devices() if devices is None else devices)}
    if len(platforms) != 1:
        raise ValueError(f"A program runs on devices of one platform, got {', '.join(sorted(platforms))}.")
    return platforms.pop()


def default_unroll(platform: str) -> int:
    """Unroll factor of the recurrent memories' replay loops: 4 on accelerators (fewer, larger kernels), 1 on CPUs."""
    return 1 if platform == "cpu" else 4


def gru_impl(hidden_size: int, platform: str) -> str:
    """How the GRU runs its time loop (`pobax.memory.GRU`'s `impl`): on GPUs the fused Pallas kernel up to 64 wide,
    else the scan with the recurrent product `recurrent_product` picks."""
    if platform == "gpu" and hidden_size <= 64:
        return "fused"
    return recurrent_product(hidden_size, platform)


def lstm_impl(hidden_size: int, platform: str) -> str:
    """How the LSTM runs its time loop (`pobax.memory.LSTM`'s `impl`): on GPUs the fused Pallas kernels up to 32
    wide (they keep the four gates' weights in registers), else the scan with the product `recurrent_product` picks."""
    if platform == "gpu" and hidden_size <= 32:
        return "fused"
    return recurrent_product(hidden_size, platform, gates=4)


def recurrent_product(hidden_size: int, platform: str, gates: int = 3) -> str:
    """How a recurrent cell's scan computes `weight_hh @ h` for a `(gates × hidden, hidden)` weight: as a
    multiply-sum that XLA fuses with the gate arithmetic ("reduce") on accelerators up to the GRU's 3 × 256² weight
    entries, else a matrix product ("dot"). Above that bound the multiply-sum is slower, and XLA's compile of the
    LSTM's 4 × 256² multiply-sum did not finish in 25 minutes."""
    return "reduce" if platform != "cpu" and gates * hidden_size**2 <= 3 * 256**2 else "dot"


def rollout_reduce_limit(platform: str) -> int:
    """Largest rows × weight entries for which a dense layer on one time step is a multiply-sum instead of a matrix
    product (`pobax.memory.matmul_t`, the rollout's layers): 2**22 on accelerators, where the multiply-sum reads the
    weight once per row and fuses with its neighbours; unbounded it loses to the matrix product for large batches.
    0 on the CPU, where the matrix product is faster."""
    return 0 if platform == "cpu" else 2**22


def orthogonal_method(platform: str) -> str:
    """How `pobax.memory.orthogonal` orthonormalises: a QR decomposition on GPUs (one cuSOLVER call), Gram–Schmidt
    elsewhere (jaxlib's CPU LAPACK QR can deadlock when several batched QRs run at once on a small machine)."""
    return "qr" if platform == "gpu" else "gram_schmidt"


def by_lowering_platform(choose, run, *args):
    """`run(choose(platform), *args)` for the platform the program is compiled for ("gpu" on CUDA and ROCm devices),
    chosen when it is lowered (`jax.lax.platform_dependent`: one branch per distinct choice is traced, only the
    lowering platform's is compiled). For choices inside code that takes no configuration, e.g. the initialisers of
    a user's memory cell."""
    platforms = {"cuda": "gpu", "rocm": "gpu", "cpu": "cpu", "tpu": "tpu"}
    choices = {name: choose(platform) for name, platform in platforms.items()}
    default = choose("other")
    branches = {c: (lambda *a, c=c: run(c, *a)) for c in {*choices.values(), default}}
    per_platform = {name: branches[c] for name, c in choices.items() if c != default}
    return jax.lax.platform_dependent(*args, **per_platform, default=branches[default])


def reset_pool_size(platform: str) -> int | None:
    """`AutoReset.pool_size` for environments whose reset costs about a step or more (RockSample, Battleship): 8 done
    environments reset per round on the CPU, a reset computed for every environment on accelerators (the pool's
    `while_loop` would synchronise with the host every step)."""
    return 8 if platform == "cpu" else None


def loop_free_placements(platform: str) -> bool:
    """Battleship resets draw ship placements in a fixed number of rounds (no `while_loop`) on accelerators, where
    the loop synchronises with the host every step; the CPU keeps the loop (no synchronisation to save, less to
    compile)."""
    return platform != "cpu"


def compiler_options(deterministic: bool = False, fast_compile: bool = False, *, platform: str | None = None) -> dict:
    """XLA options of a program for `platform` (default: JAX's default devices' platform, `platform_of`).
    `deterministic` on a GPU: XLA's deterministic ops and no autotuning by timing, so that the same seed trains the
    same run in every process on the same kind of GPU (XLA otherwise picks each GEMM's kernel by timing candidates,
    and near ties go either way from one process to the next). `fast_compile`: LLVM's optimisations off (faster
    compiles, slower steps; for tiny runs)."""
    options = {}
    if deterministic and (platform or platform_of()) == "gpu":
        options.update(xla_gpu_deterministic_ops=True, xla_gpu_autotune_level=0)
    if fast_compile:
        options.update(xla_backend_optimization_level=0, xla_llvm_disable_expensive_passes=True)
    return options


_UNSET = "platform"  # an override field left to the platform's choice


@dataclasses.dataclass(frozen=True)
class Backend:
    """The implementation choices of one program: those of `platform`, except where a field overrides one (for
    benchmarks that compare them: results agree up to float rounding, only speed differs). Hashable: it is part of
    a compiled program's static configuration. Build it with `Backend.of(devices, overrides)`."""

    platform: str = "cpu"
    gru_impl: str = _UNSET
    lstm_impl: str = _UNSET
    unroll: int | str = _UNSET
    rollout_reduce_limit: int | str = _UNSET
    reset_pool_size: int | None | str = _UNSET
    loop_free_placements: bool | str = _UNSET
    gae_method: str = _UNSET

    @staticmethod
    def of(devices=None, overrides: str | dict = "") -> "Backend":
        """The backend of a program on `devices` (default: JAX's default devices), with `overrides`: a dict, or
        comma-separated `NAME=VALUE` items (`parse_overrides`)."""
        if isinstance(overrides, str):
            overrides = parse_overrides(overrides)
        for name, value in overrides.items():
            if name not in _VALID or not _VALID[name][0](value):
                raise ValueError(f"Bad backend choice {name}={value!r}: see pobax._backend.parse_overrides.")
        return Backend(platform_of(devices), **overrides)

    def _get(self, name: str, choice):
        value = getattr(self, name)
        return choice if isinstance(value, str) and value == _UNSET else value

    def gru(self, hidden_size: int) -> str:
        """`GRU`'s `impl` for this width."""
        return self._get("gru_impl", gru_impl(hidden_size, self.platform))

    def lstm(self, hidden_size: int) -> str:
        """`LSTM`'s `impl` for this width."""
        return self._get("lstm_impl", lstm_impl(hidden_size, self.platform))

    def scan_unroll(self) -> int:
        """Unroll factor of the recurrent memories' replay loops (`default_unroll`)."""
        return self._get("unroll", default_unroll(self.platform))

    def reduce_limit(self) -> int:
        """The rollout's dense-layer bound (`rollout_reduce_limit`)."""
        return self._get("rollout_reduce_limit", rollout_reduce_limit(self.platform))

    def pool_size(self) -> int | None:
        """`AutoReset.pool_size` of environments with costly resets (`reset_pool_size`)."""
        return self._get("reset_pool_size", reset_pool_size(self.platform))

    def loop_free(self) -> bool:
        """Battleship's `loop_free` (`loop_free_placements`)."""
        return self._get("loop_free_placements", loop_free_placements(self.platform))

    def gae(self) -> str:
        """`pobax.agent.gae`'s `method` in PPO's update ("auto": by the rollout's length, on every platform)."""
        return self._get("gae_method", "auto")


_VALID = {
    "gru_impl": (lambda v: v in ("dot", "reduce", "fused"), "dot, reduce or fused"),
    "lstm_impl": (lambda v: v in ("dot", "reduce", "fused"), "dot, reduce or fused"),
    "unroll": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1, "a positive integer"),
    "rollout_reduce_limit": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
                             "a non-negative integer"),
    "reset_pool_size": (lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool) and v >= 1),
                        "a positive integer or none"),
    "loop_free_placements": (lambda v: isinstance(v, bool), "true or false"),
    "gae_method": (lambda v: v in ("auto", "weights", "associative", "sequential"),
                   "auto, weights, associative or sequential"),
}


#: Choices a `Backend` may override, as `NAME=VALUE` (`TrainConfig.backend`, the benchmarks' `--backend`).
OVERRIDES = tuple(_VALID)


def parse_overrides(text: str) -> dict:
    """`"NAME=VALUE,NAME=VALUE"` → {name: value} (empty text: none). Raises ValueError naming the bad item."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or name not in OVERRIDES:
            raise ValueError(f"Bad backend choice {item!r}: expected NAME=VALUE with NAME one of "
                             f"{', '.join(OVERRIDES)}.")
        parsed = {"true": True, "false": False, "none": None}.get(
            value.lower(), int(value) if value.lstrip("-").isdigit() else value)
        valid, want = _VALID[name]
        if not valid(parsed):
            raise ValueError(f"Bad backend choice {item!r}: {name} takes {want}.")
        out[name] = parsed
    return out
