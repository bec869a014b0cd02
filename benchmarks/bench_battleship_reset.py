"""Battleship's reset with and without the rejection `while_loop` (`pobax.env._battleship.LOOP_FREE`).

    python benchmarks/bench_battleship_reset.py                 # env-only at 1 / 32 / 8192 envs, then training
    python benchmarks/bench_battleship_reset.py --no-train --num-envs 1 64

Every environment computes a reset on every step (AutoReset keeps it where an episode ended), so the placement
sampler runs each step. `loop`: rejection rounds in a `jax.lax.while_loop` (on a GPU, a device-to-host copy of its
predicate per iteration, i.e. a host synchronisation per step); `free`: the 4 rounds unrolled (what accelerators
use). Both draw the same configurations. Prints env-only steps/s (random legal actions) and training steps/s of
Battleship GRU (1 seed, the paper's settings) for each, with the device and the JAX version.
"""

import argparse
import os
import sys

import jax

sys.path.insert(0, os.path.dirname(__file__))
import bench_env  # noqa: E402
import bench_train  # noqa: E402

import pobax.env._battleship as B  # noqa: E402
from pobax.agent import train  # noqa: E402
from pobax.agent._train import clear_compiled  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 32, 8192])
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--updates", type=int, default=60)
    p.add_argument("--no-train", action="store_true")
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}")
    for mode, loop_free in (("loop", False), ("free", True)):
        B.LOOP_FREE = loop_free
        clear_compiled()  # LOOP_FREE is read when tracing: trace and compile afresh
        for n in args.num_envs:
            r = bench_env.bench("battleship_10", n, args.steps)
            print(f"{mode:5s} env-only {n:6d} envs {r['steps_per_s']:14,.0f} steps/s  compile {r['compile_s']:.1f} s",
                  flush=True)
        if not args.no_train:
            r = train(bench_train.case_config("battleship_10", "gru", 1, args.updates), save=False, progress=False)
            print(f"{mode:5s} train battleship_10:gru:1 {r.steps_per_s:14,.0f} steps/s  compile {r.compile_s:.1f} s",
                  flush=True)

if __name__ == "__main__":
    main()
