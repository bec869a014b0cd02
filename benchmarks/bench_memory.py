"""Device memory and parameters of a benchmark agent: the compiled chunk program's buffers, without training.

    python benchmarks/bench_memory.py --cases Navix-DMLab-Maze-03-v0:ceiling rocksample_15_15:trxl
    python benchmarks/bench_memory.py --cases battleship_10:gru --budget paper --json mem.json
    python benchmarks/bench_memory.py --cases Navix-DMLab-Maze-03-v0:ceiling --observability full   # the map
    python benchmarks/bench_memory.py --cases battleship_10:gru battleship_10:trxl --set embed_size=256 --params-only

A case is ENV:AGENT (AGENT: floor, gru, ld, trxl, ceiling, or a memory of the zoo), configured as `pobax benchmark`
would at `--budget` (`--observability`: on that observation instead of the agent's own). For each, the training state
is initialised and the chunk program (one update) compiled on the default backend; XLA's memory analysis gives the
bytes of its arguments (the training state of every run), its temporaries (rollout buffer, minibatches, activations
and gradients of the replay) and its outputs. A chunk of more updates runs the same update in a loop, so its peak is
the same. `parameters` counts the network of one run (`memory_parameters`: its memory cell's); `--params-only` counts
them without compiling. `--set KEY=VALUE` sets a structural training option of every case, e.g. `embed_size=256` for
the Transformer-XL of the paper's default table. What the GPU needs is about arguments + temporaries (the state is
donated, so the output reuses the arguments' buffers); several processes sharing a GPU need the sum. Figures from the
CPU backend differ from a GPU's (other fusion and buffer assignment) but are of the same order.
"""

import dataclasses
import json
import sys

import equinox as eqx
import jax
import numpy as np

from pobax._cli.args import ScriptParser
from pobax.agent import _train
from pobax._cli.training import _parse_axes
from pobax.agent._ppo import make_model
from pobax.env import DictSpace
from pobax.eval import benchmark_plan
from pobax.eval._gap import AGENTS


def _count(tree) -> int:
    """Parameters of a network built abstractly (`eqx.filter_eval_shape`: shapes, no initialisation)."""
    return sum(int(x.size) for x in jax.tree_util.tree_leaves(tree) if isinstance(x, jax.ShapeDtypeStruct))


def _space(space) -> dict:
    """The observation's shape and dtype; a dictionary space (Battleship's observation and action mask) per entry."""
    if isinstance(space, DictSpace):
        return {k: _space(v) for k, v in space.spaces.items()}
    return {"shape": list(space.shape), "dtype": str(np.dtype(space.dtype))}


def _shown(space: dict) -> str:
    if "shape" in space:
        return "×".join(map(str, space["shape"])) + " " + space["dtype"]
    return " + ".join(_shown(v) for v in space.values())


def measure(env: str, agent: str, budget: str, observability: str | None = None, overrides: dict | None = None,
            params_only: bool = False) -> dict:
    own = agent in AGENTS
    cfg = benchmark_plan((env,), budget, (agent,) if own else (), memories=() if own else (agent,),
                         overrides=overrides)[0].config
    if observability is not None:
        cfg = dataclasses.replace(cfg, observability=observability)
    runs = _train.Runs(cfg)
    model = eqx.filter_eval_shape(make_model, cfg, runs.env, jax.random.key(0))
    row = {"env": env, "agent": agent, "budget": budget, "runs": runs.num_runs, "memory": cfg.memory,
           "hidden_size": cfg.hidden_size, "embed_size": cfg.embed_size, "num_envs": cfg.num_envs,
           "observability": cfg.observability, "observation": _space(runs.env.observation_space),
           "parameters": _count(model), "memory_parameters": _count(model.memory)}
    if params_only:
        return row
    state = runs.init()
    # the chunk program exactly as `Runs.chunks` builds it (its XLA options too)
    analysis = runs.chunk_program().lower(runs.fixed(0, chunk_len=1), state).compile().compiled.memory_analysis()
    return row | {"argument_bytes": analysis.argument_size_in_bytes, "temp_bytes": analysis.temp_size_in_bytes,
                  "output_bytes": analysis.output_size_in_bytes}


def main() -> None:
    p = ScriptParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", nargs="+", default=["Navix-DMLab-Maze-01-v0:ceiling"])
    p.add_argument("--budget", default="reduced", choices=["smoke", "reduced", "paper"])
    p.add_argument("--observability", default=None,
                   help="every case on this observation instead of its agent's (e.g. full: the mazes' map)")
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                   help="structural training options of every case, e.g. embed_size=256 (read as --axis reads them)")
    p.add_argument("--params-only", action="store_true", help="count parameters only: no compilation")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    try:  # read as the field's type, as `pobax train --axis` reads a structural field
        axes = _parse_axes(tuple(args.set))
    except ValueError as e:
        print(f"error: --set: {e}", file=sys.stderr)
        sys.exit(2)
    if any(len(v) > 1 for v in axes.values()):
        print("error: --set takes one value per field (KEY=VALUE)", file=sys.stderr)
        sys.exit(2)
    overrides = {k: v[0] for k, v in axes.items()}
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, budget {args.budget}")
    print(f"{'case':40s} {'runs':>5s} {'observation':>26s} {'parameters':>11s} {'of memory':>10s}"
          + ("" if args.params_only else f" {'state GiB':>10s} {'temp GiB':>9s}"))
    rows = []
    for case in args.cases:
        env, _, agent = case.rpartition(":")
        if not env:
            sys.exit(f"error: case {case!r} is not ENV:AGENT (e.g. tmaze_10:gru)")
        try:
            r = measure(env, agent, args.budget, args.observability, overrides, args.params_only)
        except ValueError as e:  # a configuration pobax refuses (an unknown field, a value out of range): one line
            print(f"error: {case}: {e}", file=sys.stderr)
            sys.exit(2)
        rows.append(r)
        obs = _shown(r["observation"])
        gib = "" if args.params_only else f" {r['argument_bytes'] / 2**30:>10.2f} {r['temp_bytes'] / 2**30:>9.2f}"
        print(f"{case:40s} {r['runs']:>5d} {obs:>26s} {r['parameters']:>11,d} {r['memory_parameters']:>10,d}{gib}",
              flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
                       "command": " ".join(["python", *sys.argv]), "overrides": overrides, "cases": rows},
                      f, indent=2)


if __name__ == "__main__":
    main()
