"""T-Maze 10 at the paper's settings, one run per process-level program (so the 1-seed rules apply: on an NVIDIA GPU
one Triton tiling for every GEMM, `pobax.agent._train.TILING_MAX_HIDDEN`): GRU against memoryless, per seed.

    python benchmarks/tmaze_single_runs.py --seeds 0 1 2

Prints each run's final discounted and undiscounted return (mean over the last 10% of updates), env steps/s and
compile seconds: the learning result must be the foundation issue's (GRU solves T-Maze, memoryless does not).
"""

import argparse
import dataclasses

import jax

from pobax.agent import TrainConfig, train
from pobax.agent._presets import apply_preset, paper_preset


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--total-steps", type=int, default=None, help="default: the paper's (1M)")
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind}, jax {jax.__version__}")
    for memory in ("gru", "memoryless"):
        for seed in args.seeds:
            cfg = TrainConfig(env="tmaze_10", memory=memory, action_concat=memory != "memoryless", seed=seed, num_seeds=1)
            cfg = apply_preset(cfg, paper_preset("tmaze_10", memory))
            if args.total_steps:
                cfg = dataclasses.replace(cfg, total_steps=args.total_steps)
            r = train(cfg, save=False, progress=False)
            s = r.summary["sets"][0]
            print(f"{memory:10s} seed {seed}: final disc return {s['disc_return']['mean']:.3f}, return "
                  f"{s['return']['mean']:.3f}, {r.steps_per_s:,.0f} env steps/s, compile {r.compile_s:.1f} s", flush=True)


if __name__ == "__main__":
    main()
