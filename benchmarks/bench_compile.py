"""Compile seconds of random draws and of training's initialisation program (with XLA's optimisations unless
`--fast-compile`).

    python benchmarks/bench_compile.py                                   # the default shapes and cases
    python benchmarks/bench_compile.py --shapes 32x3x7x7 96x32 --cases Navix-DMLab-Maze-02-v0:memoryless:full

Draws: for each SHAPE (axes joined by `x`), `jax.random.uniform` and `jax.random.normal` of that shape, then the
same values drawn flat and reshaped (`pobax.memory.flat_draw`, which pobax's initialisers use), each compiled alone;
the script checks that both give the same values. Cases: `ENV:MEMORY[:OBSERVABILITY]` at the `smoke` budget's
sizes with `--seeds` runs (`pobax.agent.Runs.init`'s program: every run's network, optimiser and environments),
compiled afresh per case. The figures are the seconds of `jax.jit(...).lower(...).compile()` (the persistent
compilation cache off).
"""

import time

import jax
import numpy as np

from pobax._cli.args import ScriptParser
from pobax.agent import TrainConfig
from pobax.agent._train import Runs, _init_runs, structural
from pobax.eval._protocol import smoke_settings
from pobax.memory import flat_draw


def compile_seconds(fn, *args, options: dict | None = None) -> float:
    t0 = time.perf_counter()
    jax.jit(fn, compiler_options=options).lower(*args).compile()
    return time.perf_counter() - t0


def draws(shapes: list[tuple[int, ...]]) -> None:
    print(f"{'draw':10s} {'shape':>14s} {'shaped s':>9s} {'flat s':>7s}  same values")
    key = jax.random.key(0)
    for shape in shapes:
        for name, sample in (("uniform", jax.random.uniform), ("normal", jax.random.normal)):
            shaped = lambda k: sample(k, shape)  # noqa: E731
            flat = lambda k: flat_draw(sample, k, shape)  # noqa: E731
            jax.clear_caches()
            a, b = compile_seconds(shaped, key), compile_seconds(flat, key)
            same = np.array_equal(jax.jit(shaped)(key), jax.jit(flat)(key))
            print(f"{name:10s} {'x'.join(map(str, shape)):>14s} {a:9.2f} {b:7.2f}  {same}", flush=True)


def init_programs(cases: list[str], seeds: int, fast_compile: bool = False) -> None:
    print(f"{'case':48s} {'runs':>5s} {'init compile s':>15s}")
    for case in cases:
        env, memory, *obs = case.split(":")
        observability = obs[0] if obs else "partial"
        settings = {**smoke_settings(env, observability, "auto"), "num_seeds": seeds, "fast_compile": fast_compile}
        cfg = TrainConfig(env=env, memory=memory, observability=observability, **settings)
        runs = Runs(cfg)
        scfg = structural(cfg, runs.backend)
        jax.clear_caches()
        s = compile_seconds(lambda kd: _init_runs(scfg, runs.backend, runs.env, kd), runs.key_data,
                            options=runs.options or None)
        print(f"{case:48s} {runs.num_runs:5d} {s:15.1f}", flush=True)


def main() -> None:
    p = ScriptParser(description=__doc__.splitlines()[0])
    p.add_argument("--shapes", nargs="*", default=["4704", "32x3x7x7", "32x32x3x3", "96x32"],
                   help="draw shapes, axes joined by x")
    p.add_argument("--cases", nargs="*", default=["Navix-DMLab-Maze-02-v0:memoryless:full", "tmaze_10:gru"],
                   help="ENV:MEMORY[:OBSERVABILITY] whose initialisation program to compile")
    p.add_argument("--seeds", type=int, default=8, help="runs per case's program")
    p.add_argument("--fast-compile", action="store_true", help="the cases' programs without LLVM's optimisations "
                   "(`TrainConfig.fast_compile`, as the smoke budget compiles most agents)")
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), JAX {jax.__version__}")
    if not all(n.isdigit() and int(n) > 0 for s in args.shapes for n in s.split("x")):
        raise SystemExit("--shapes: axes are positive numbers joined by x, e.g. 32x3x7x7")
    shapes = [tuple(int(n) for n in s.split("x")) for s in args.shapes]
    draws(shapes)
    init_programs(args.cases, args.seeds, args.fast_compile)


if __name__ == "__main__":
    main()
