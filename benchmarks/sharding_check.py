"""Runs sharded over several devices: the same (sets × seeds) batch trained on 1 device and on all local
devices; prints throughput, compile time, where the state lives, and the largest metric difference.

    python benchmarks/sharding_check.py --env tmaze_10 --memory gru --seeds 16 --total-steps 200000
"""

import argparse
import time

import jax
import numpy as np

from pobax.agent import TrainConfig, train


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="tmaze_10")
    p.add_argument("--memory", default="gru")
    p.add_argument("--seeds", type=int, default=16)
    p.add_argument("--total-steps", type=int, default=200_000)
    a = p.parse_args()
    cfg = TrainConfig(env=a.env, memory=a.memory, action_concat=True, hidden_size=32, num_seeds=a.seeds,
                      total_steps=a.total_steps, lr=(2.5e-3, 2.5e-4), lambda0=(0.7, 0.95), num_chunks=4)
    devs = jax.local_devices()
    print(f"{len(devs)} × {devs[0].device_kind}, jax {jax.__version__}; {len(cfg.grid())} sets × {a.seeds} seeds "
          f"= {len(cfg.grid()) * a.seeds} runs of {a.env} {a.memory}", flush=True)
    results = {}
    for n in sorted({1, len(devs)}):
        t0 = time.perf_counter()
        r = train(cfg, save=False, progress=False, devices=devs[:n])
        leaf = jax.tree.leaves(r.state.model)[0]
        placed = sorted({d.id for d in leaf.sharding.device_set})
        print(f"  {n} device(s): {r.steps_per_s:12,.0f} env steps/s  compile {r.compile_s:5.1f} s  "
              f"wall {time.perf_counter() - t0:6.1f} s  parameters on devices {placed}", flush=True)
        results[n] = r.metrics
    if len(results) == 2:
        m1, m2 = results[1], results[len(devs)]
        for col in ("disc_return", "pg_loss", "v_loss"):
            d = np.nanmax(np.abs(m1[col].to_numpy() - m2[col].to_numpy()))
            print(f"  max |{col}(1 device) - {col}({len(devs)} devices)| = {d:.3g}", flush=True)


if __name__ == "__main__":
    main()
