"""Training throughput: env steps/s and compile seconds of the compiled, vmapped PPO loop.

    python benchmarks/bench_train.py                       # T-Maze 10 GRU at 1 and 10 seeds, memoryless at 1 and 10
    python benchmarks/bench_train.py --cases tmaze_10:gru:30 tmaze_10:memoryless:30 --updates 200

A case is ENV:MEMORY:SEEDS[:OBSERVABILITY] (MEMORY: memoryless, gru, trxl, or ld for λ-discrepancy on a GRU;
OBSERVABILITY defaults to partial); the network and PPO sizes are the paper's for the environment (T-Maze: hidden 32,
4 envs × 128 steps, 4 minibatches, 4 epochs; action concatenation for memory agents). SEEDS `Nxgrid` (e.g.
`tmaze_10:gru:5xgrid`) trains N seeds of every set of the paper's sweep (`pobax.eval.PAPER_GRID`: 4 learning rates
× 6 λ0 = 24 sets), all vmapped in one program, as `pobax sweep` does. Each case trains for `--updates` updates
split into 4 chunks; compile seconds = first chunk − a steady chunk, steps/s counts every run's environment steps
over the steady chunks ("per run": divided by the runs). Prints the device and the JAX version.

`--gru dot reduce fused` compares the implementations of the GRU's time loop (`pobax.memory._gru.RECURRENT_IMPL`),
`--scan-vjp manual autodiff` the backward of its scan (`pobax.memory._gru.SCAN_VJP`), `--gae weights associative sequential`
the advantage recursion (`pobax.agent._gae.GAE_METHOD`).
"""

import argparse
import json

import jax

import pobax.agent._gae as gae_mod
import pobax.memory._gru as gru_mod
from pobax.agent import TrainConfig, train
from pobax.agent._train import clear_compiled, run_layout
from pobax.env import spec
from pobax.eval import PAPER_GRID


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
                **sizes: int) -> TrainConfig:
    """The case's TrainConfig at the paper's settings; `sizes` (`hidden_size`, `embed_size`, `num_envs`) replace
    the environment's recommended ones, for the same number of updates. `grid`: the paper's sweep values
    (`PAPER_GRID`) for the numeric hyperparameters it names, every combination a vmapped set of `seeds` runs."""
    rec = {**spec(env).recommended, **sizes}
    num_envs = rec.get("num_envs", 4)
    fields = {k: v for k, v in rec.items() if k in ("hidden_size", "embed_size")}
    if isinstance(rec.get("entropy_coeff"), float):
        fields["entropy_coeff"] = (rec["entropy_coeff"],)
    if grid:
        fields.update(PAPER_GRID)
    double_critic = memory == "ld"  # λ-discrepancy: GRU with two critics
    memory = "gru" if double_critic else memory
    return TrainConfig(
        env=env, observability=observability, memory=memory, double_critic=double_critic, action_concat=memory != "memoryless", num_envs=num_envs, num_steps=128,
        num_minibatches=min(4, num_envs), total_steps=updates * num_envs * 128, num_seeds=seeds, num_chunks=4,
        unroll=unroll, rollout_unroll=rollout_unroll,
        **fields,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["tmaze_10:gru:1", "tmaze_10:gru:10", "tmaze_10:memoryless:1",
                                                  "tmaze_10:memoryless:10"])
    p.add_argument("--updates", type=int, default=100)
    p.add_argument("--unroll", type=int, nargs="+", default=[None],
                   help="GRU replay unroll factors to compare (default: the library's, 1 on CPU and 4 on GPU)")
    p.add_argument("--rollout-unroll", type=int, nargs="+", default=[1],
                   help="rollout unroll factors to compare (TrainConfig.rollout_unroll, default 1)")
    p.add_argument("--gru", nargs="+", default=[gru_mod.RECURRENT_IMPL], choices=["auto", "dot", "reduce", "fused"],
                   help="GRU time-loop implementations to compare (pobax.memory._gru.RECURRENT_IMPL)")
    p.add_argument("--scan-vjp", nargs="+", default=[gru_mod.SCAN_VJP], choices=["manual", "autodiff"],
                   help="backward of the GRU's scan to compare (pobax.memory._gru.SCAN_VJP)")
    p.add_argument("--gae", nargs="+", default=[gae_mod.GAE_METHOD], choices=["weights", "associative", "sequential"],
                   help="GAE recursions to compare (pobax.agent._gae.GAE_METHOD)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    device = f"{jax.devices()[0].device_kind} ({jax.default_backend()})"
    print(f"device: {device}, jax {jax.__version__}")
    print(f"{'case':32s} {'env steps/s':>14s} {'per run':>12s} {'compile s':>10s}")
    rows = []
    for case, unroll, runroll, gimpl, vjp, gm in [(c, u, r, g, v, m) for c in args.cases for u in args.unroll
                                                  for r in args.rollout_unroll for g in args.gru
                                                  for v in args.scan_vjp for m in args.gae]:
        env, memory, seeds, grid, obs = parse_case(case)
        cfg = case_config(env, memory, seeds, args.updates, unroll, *obs, rollout_unroll=runroll, grid=grid)
        runs = len(run_layout(cfg)[0])
        gru_mod.RECURRENT_IMPL, gru_mod.SCAN_VJP, gae_mod.GAE_METHOD = gimpl, vjp, gm
        clear_compiled()  # the implementation is read when tracing: trace and compile each case afresh
        case = case if len(args.unroll) == 1 else f"{case} unroll={unroll}"
        case = case if len(args.rollout_unroll) == 1 else f"{case} rollout_unroll={runroll}"
        case = case if len(args.gru) == 1 else f"{case} gru={gimpl}"
        case = case if len(args.scan_vjp) == 1 else f"{case} vjp={vjp}"
        case = case if len(args.gae) == 1 else f"{case} gae={gm}"
        r = train(cfg, save=False, progress=False)
        row = dict(case=case, env=env, memory=memory, seeds=seeds, runs=runs, steps_per_s=r.steps_per_s,
                   steps_per_s_per_run=r.steps_per_s / runs, compile_s=r.compile_s, device=device,
                   jax=jax.__version__, hidden_size=cfg.hidden_size, num_envs=cfg.num_envs, unroll=unroll,
                   rollout_unroll=runroll, gru=gimpl,
                   scan_vjp=vjp, gae=gm)
        rows.append(row)
        print(f"{case:32s} {r.steps_per_s:14,.0f} {r.steps_per_s / runs:12,.0f} {r.compile_s:10.1f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
