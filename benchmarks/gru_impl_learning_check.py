"""Learning must not change with how the network is computed: T-Maze 10 GRU at the paper's settings, trained once
per `pobax.memory._gru.RECURRENT_IMPL` (`--impls`) and per `pobax.memory._layers.REDUCE_MAX_WORK` (`--dense`:
0 = the rollout's dense layers as GEMMs, `default` = the library's choice), same seeds; prints the final discounted
return (mean [95% CI] over seeds), the largest difference between the first two learning curves, throughput and
compile time.

    python benchmarks/gru_impl_learning_check.py --impls dot fused --seeds 10 --steps 1000000
    python benchmarks/gru_impl_learning_check.py --impls auto --dense 0 default
"""

import argparse
import dataclasses
import json

import jax
import numpy as np

import pobax.memory._gru as gru_mod
import pobax.memory._layers as layers_mod
from pobax.agent import TrainConfig, apply_preset, paper_preset, train
from pobax.agent._train import clear_compiled


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="tmaze_10")
    p.add_argument("--impls", nargs="+", default=["dot", "fused"], choices=["auto", "dot", "reduce", "fused"])
    p.add_argument("--dense", nargs="+", default=["default"], help="REDUCE_MAX_WORK values (an integer or default)")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--steps", type=int, default=1_000_000)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}")
    base = apply_preset(TrainConfig(env=args.env, memory="gru"), paper_preset(args.env, "gru"))
    cfg = dataclasses.replace(base, num_seeds=args.seeds, total_steps=args.steps)
    rows, curves = [], {}
    for impl in args.impls:
        for dense in args.dense:
            gru_mod.RECURRENT_IMPL = impl
            layers_mod.REDUCE_MAX_WORK = None if dense == "default" else int(dense)
            clear_compiled()  # both are read when tracing: trace and compile afresh
            r = train(cfg, save=False, progress=False)
            s = r.summary["sets"][0]["disc_return"]
            name = impl if len(args.dense) == 1 else f"{impl}/dense={dense}"
            curves[name] = r.metrics.groupby("update")["disc_return"].mean().to_numpy()
            rows.append(dict(impl=impl, dense=dense, disc_return=s, steps_per_s=r.steps_per_s, compile_s=r.compile_s))
            print(f"{name:16s} final discounted return {s['mean']:.3f} [{s['ci_low']:.3f}, {s['ci_high']:.3f}]  "
                  f"{r.steps_per_s:,.0f} env steps/s  compile {r.compile_s:.1f} s", flush=True)
    if len(curves) > 1:
        a, b = list(curves.values())[:2]
        print(f"max |Δ| of the seed-mean learning curves ({' vs '.join(list(curves)[:2])}): "
              f"{np.nanmax(np.abs(a - b)):.4f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
