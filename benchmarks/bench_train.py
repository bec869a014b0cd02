"""Training throughput: env steps/s and compile seconds of the compiled PPO loop (`pobax.eval.train`).

    python benchmarks/bench_train.py                       # T-Maze 10 GRU at 1 and 10 seeds, memoryless at 1 and 10
    python benchmarks/bench_train.py --cases tmaze_10:gru:30 tmaze_10:memoryless:30 --updates 200 --json out.json
    python benchmarks/bench_train.py --cases tmaze_10:gru:30 --backend default gru_impl=dot   # A/B in one process

A case is ENV:MEMORY:SEEDS[:OBSERVABILITY] (MEMORY: memoryless, gru, trxl, or ld for λ-discrepancy on a GRU;
OBSERVABILITY defaults to partial). The network and PPO sizes are the paper's own for the environment
(`spec(env).recommended`, with `spec(env).paper_original["recommended"]` where the registry recommends otherwise,
e.g. RockSample 11's 8 environments per seed, not 32), so that the figures compare with the original
implementation's: T-Maze hidden 32, 4 envs × 128 steps, 4 minibatches, 4 epochs; action concatenation for memory
agents. SEEDS `Nxgrid` (e.g. `tmaze_10:gru:5xgrid`) trains N seeds of every set of the paper's sweep
(`pobax.eval.PAPER_GRID`: 4 learning rates × 6 λ0 = 24 sets), all in one program, as `pobax sweep` does.

Each case trains for `--updates` updates split into 4 chunks, in this process, the persistent compilation cache off
(unless JAX is configured otherwise). `compile s` is `TrainResult.compile_s` (everything a run pays before steady
training: both programs' compilation, the initialisation, and the first chunk's time beyond a steady chunk's);
`env steps/s` counts every run's environment steps over the steady chunks (median), "per run" divides by the runs.

`--deterministic` sets `TrainConfig.deterministic` (on a GPU: XLA's deterministic ops and no autotuning by timing),
`--fast-compile` `TrainConfig.fast_compile`. `--backend` compares the library's implementation choices
(`pobax/_backend.py`) through `TrainConfig.backend`: each argument is one variant, `default` (the platform's choices)
or comma-separated NAME=VALUE items (e.g. `gru_impl=dot`, `rollout_reduce_limit=0`, `loop_free_placements=false`),
every case trained once per variant.
`--embed-size N` sets the Transformer-XL embedding of every case (an A/B against a tree whose registry used N).
`--num-envs 4 64` trains every case at each number of environments per run (the throughput grid of a new
environment). `--devices 1 2` trains every case sharded over the first 1, then the first 2 devices
(`train(..., devices=...)`; default: every device), for the scaling table of several GPUs.
Prints the device and the JAX version; `--json PATH` writes them with every case's figures.
"""

import argparse
import datetime
import itertools
import json
import sys

import jax

from pobax._cli.args import ScriptParser
from pobax._backend import parse_overrides
from pobax.agent import TrainConfig, run_layout
from pobax.env import spec
from pobax.eval import PAPER_GRID, train


def parse_case(case: str) -> tuple[str, str, int, bool, list[str]]:
    """`ENV:MEMORY:SEEDS[:OBSERVABILITY]` → (env, memory, seeds, grid, [observability]); SEEDS is `N` or `Nxgrid`."""
    parts = case.split(":")
    seeds = parts[2] if len(parts) > 2 else ""
    n, grid = (seeds[: -len("xgrid")], True) if seeds.endswith("xgrid") else (seeds, False)
    if len(parts) not in (3, 4) or not n.isdigit() or int(n) < 1:
        raise SystemExit(f"bad case {case!r}: expected ENV:MEMORY:SEEDS[:OBSERVABILITY] with SEEDS a positive "
                         "number, or N followed by 'xgrid' for N seeds of the paper's grid (e.g. tmaze_10:gru:5xgrid)")
    return parts[0], parts[1], int(n), grid, parts[3:]


def case_config(env: str, memory: str, seeds: int, updates: int, unroll: int | None = None,
                observability: str = "partial", rollout_unroll: int = 1, grid: bool = False,
                deterministic: bool = False, fast_compile: bool = False, backend: str = "",
                **sizes: int) -> TrainConfig:
    """The case's TrainConfig at the paper's settings; `sizes` (`hidden_size`, `embed_size`, `num_envs`) replace
    the environment's, for the same number of updates. `grid`: the paper's sweep values (`PAPER_GRID`) for the
    numeric hyperparameters it names, every combination a set of `seeds` runs in the same program."""
    s = spec(env)
    rec = {**s.recommended, **s.paper_original.get("recommended", {}), **sizes}
    num_envs = rec.get("num_envs", 4)
    fields = {k: v for k, v in rec.items() if k in ("hidden_size", "embed_size")}
    if isinstance(rec.get("entropy_coeff"), float):
        fields["entropy_coeff"] = rec["entropy_coeff"]
    if grid:
        fields.update(PAPER_GRID)
    double_critic = memory == "ld"  # λ-discrepancy: GRU with two critics
    memory = "gru" if double_critic else memory
    return TrainConfig(
        env=env, observability=observability, memory=memory, double_critic=double_critic,
        action_concat=memory != "memoryless", num_envs=num_envs, num_steps=128, num_minibatches=min(4, num_envs),
        total_steps=updates * num_envs * 128, num_seeds=seeds, num_chunks=4, unroll=unroll,
        rollout_unroll=rollout_unroll, deterministic=deterministic, fast_compile=fast_compile, backend=backend,
        **fields,
    )


def variant_overrides(variant: str) -> str:
    """`default` → "" (the platform's choices); `NAME=VALUE,NAME=VALUE` → itself (`TrainConfig.backend`), checked."""
    if variant in ("", "default"):
        return ""
    try:
        parse_overrides(variant)
    except ValueError as e:
        raise SystemExit(f"--backend: {e}") from None
    return variant


def device_name() -> str:
    return f"{jax.devices()[0].device_kind} ({jax.devices()[0].platform})"


def main():
    p = ScriptParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["tmaze_10:gru:1", "tmaze_10:gru:10", "tmaze_10:memoryless:1",
                                                  "tmaze_10:memoryless:10"])
    p.add_argument("--updates", type=int, default=100, help="PPO updates per case (4 chunks; at least 2)")
    p.add_argument("--unroll", type=int, nargs="+", default=[None],
                   help="GRU replay unroll factors to compare (default: the library's, 1 on CPU and 4 on GPU)")
    p.add_argument("--rollout-unroll", type=int, nargs="+", default=[1],
                   help="rollout unroll factors to compare (TrainConfig.rollout_unroll, default 1)")
    p.add_argument("--deterministic", action="store_true", help="TrainConfig.deterministic (GPU: deterministic ops)")
    p.add_argument("--fast-compile", action="store_true", help="TrainConfig.fast_compile (LLVM optimisations off)")
    p.add_argument("--backend", nargs="+", default=["default"], metavar="VARIANT",
                   help="variants of pobax/_backend.py's choices: 'default' or NAME=VALUE[,NAME=VALUE...]")
    p.add_argument("--num-envs", type=int, nargs="+", default=[None],
                   help="environments per run for every case, instead of the paper's (e.g. the registry's 32 for "
                        "RockSample 11); several values: each case at each")
    p.add_argument("--embed-size", type=int, default=None, metavar="N",
                   help="Transformer-XL embedding size for every case, instead of the paper's (e.g. 12 for the "
                        "registry's T-Maze)")
    p.add_argument("--devices", type=int, nargs="+", default=[None], metavar="N",
                   help="shard each case over the first N devices, for each N given (default: every device)")
    p.add_argument("--json", default=None, metavar="PATH", help="write device, JAX version and every case's figures")
    args = p.parse_args()
    if args.updates < 2:
        raise SystemExit("--updates must be at least 2 (steps/s is measured over the chunks after the first)")
    variants = [(v, variant_overrides(v)) for v in args.backend]
    meta = dict(device=device_name(), backend=jax.devices()[0].platform, jax=jax.__version__,
                date=datetime.date.today().isoformat(), command=" ".join(["python"] + sys.argv),
                updates=args.updates, deterministic=args.deterministic, fast_compile=args.fast_compile)
    print(f"device: {meta['device']}, jax {meta['jax']}", flush=True)
    print(f"{'case':40s} {'runs':>5s} {'env steps/s':>14s} {'per run':>12s} {'compile s':>10s}", flush=True)
    rows = []
    combos = itertools.product(args.cases, args.unroll, args.rollout_unroll, variants, args.devices, args.num_envs)
    varied = {name: len(values) > 1 for name, values in
              (("unroll", args.unroll), ("rollout_unroll", args.rollout_unroll), ("variant", variants),
               ("devices", args.devices), ("num_envs", args.num_envs))}
    for case, unroll, runroll, (variant, overrides), ndev, num_envs in combos:
        env, memory, seeds, in_grid, obs = parse_case(case)
        cfg = case_config(env, memory, seeds, args.updates, unroll, *obs, rollout_unroll=runroll, grid=in_grid,
                          deterministic=args.deterministic, fast_compile=args.fast_compile, backend=overrides,
                          **({} if num_envs is None else {"num_envs": num_envs}),
                          **({} if args.embed_size is None else {"embed_size": args.embed_size}))
        runs = len(run_layout(cfg)[0])
        jax.clear_caches()  # every case compiles afresh
        label = case
        label += f" unroll={unroll}" if varied["unroll"] else ""
        label += f" rollout_unroll={runroll}" if varied["rollout_unroll"] else ""
        label += f" {variant}" if varied["variant"] else ""
        label += f" devices={ndev or jax.device_count()}" if varied["devices"] else ""
        label += f" envs={cfg.num_envs}" if varied["num_envs"] else ""
        devices = None if ndev is None else jax.devices()[:ndev]
        r = train(cfg, save=False, progress=False, devices=devices)
        row = dict(case=label, env=env, memory=memory, seeds=seeds, grid=in_grid, runs=runs,
                   observability=cfg.observability, steps_per_s=r.steps_per_s, steps_per_s_per_run=r.steps_per_s / runs,
                   compile_s=r.compile_s, wall_s=r.summary.get("wall_s"),
                   nonfinite_updates=int((r.metrics["nonfinite"] > 0).sum()), hidden_size=cfg.hidden_size,
                   embed_size=cfg.embed_size,
                   num_envs=cfg.num_envs, unroll=unroll, rollout_unroll=runroll, backend=parse_overrides(overrides),
                   devices=ndev or jax.device_count())
        rows.append(row)
        print(f"{label:40s} {runs:5d} {r.steps_per_s:14,.0f} {r.steps_per_s / runs:12,.0f} {r.compile_s:10.1f}",
              flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(meta, cases=rows), f, indent=2)


if __name__ == "__main__":
    main()
