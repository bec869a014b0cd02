"""Device memory of a benchmark agent: the compiled chunk program's buffers, without training.

    python benchmarks/bench_memory.py --cases Navix-DMLab-Maze-03-v0:ceiling rocksample_15_15:trxl
    python benchmarks/bench_memory.py --cases battleship_10:gru --budget paper --json mem.json
    python benchmarks/bench_memory.py --cases Navix-DMLab-Maze-03-v0:ceiling --observability full   # the map

A case is ENV:AGENT (AGENT: floor, gru, ld, trxl, ceiling, or a memory of the zoo), configured as `pobax benchmark`
would at `--budget` (`--observability`: on that observation instead of the agent's own). For each, the training
state is initialised and the chunk program (one update) compiled on the default backend; XLA's memory analysis gives
the bytes of its arguments (the training state of every run), its temporaries (rollout buffer, minibatches,
activations and gradients of the replay) and its outputs. A chunk of more updates runs the same update in a loop, so
its peak is the same. What the GPU needs is about arguments + temporaries (the state is donated, so the output
reuses the arguments' buffers); several processes sharing a GPU need the sum. Figures from the CPU backend differ
from a GPU's (other fusion and buffer assignment) but are of the same order.
"""

import argparse
import dataclasses
import json
import sys

import jax
import numpy as np

from pobax.agent import _train
from pobax.eval import benchmark_plan
from pobax.eval._gap import AGENTS


def measure(env: str, agent: str, budget: str, observability: str | None = None) -> dict:
    own = agent in AGENTS
    cfg = benchmark_plan((env,), budget, (agent,) if own else (), memories=() if own else (agent,))[0].config
    if observability is not None:
        cfg = dataclasses.replace(cfg, observability=observability)
    runs = _train.Runs(cfg)
    state = runs.init()
    # the chunk program exactly as `Runs.chunks` builds it (its XLA options too)
    analysis = runs.chunk_program().lower(runs.fixed(0, chunk_len=1), state).compile().compiled.memory_analysis()
    return {"env": env, "agent": agent, "budget": budget, "runs": runs.num_runs,
            "num_envs": cfg.num_envs, "observability": cfg.observability, "obs_shape": list(runs.env.observation_space.shape),
            "obs_dtype": str(np.dtype(runs.env.observation_space.dtype)),
            "argument_bytes": analysis.argument_size_in_bytes, "temp_bytes": analysis.temp_size_in_bytes,
            "output_bytes": analysis.output_size_in_bytes}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", nargs="+", default=["Navix-DMLab-Maze-01-v0:ceiling"])
    p.add_argument("--budget", default="reduced", choices=["smoke", "reduced", "paper"])
    p.add_argument("--observability", default=None,
                   help="every case on this observation instead of its agent's (e.g. full: the mazes' map)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, budget {args.budget}")
    print(f"{'case':40s} {'runs':>5s} {'observation':>22s} {'state GiB':>10s} {'temp GiB':>9s}")
    rows = []
    for case in args.cases:
        env, _, agent = case.rpartition(":")
        if not env:
            sys.exit(f"error: case {case!r} is not ENV:AGENT (e.g. tmaze_10:gru)")
        r = measure(env, agent, args.budget, args.observability)
        rows.append(r)
        obs = "×".join(map(str, r["obs_shape"])) + " " + r["obs_dtype"]
        print(f"{case:40s} {r['runs']:>5d} {obs:>22s} {r['argument_bytes'] / 2**30:>10.2f} "
              f"{r['temp_bytes'] / 2**30:>9.2f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__, "cases": rows},
                      f, indent=2)


if __name__ == "__main__":
    main()
