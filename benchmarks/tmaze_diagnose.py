"""T-Maze diagnostics: per-seed final returns, episode lengths, entropy, and the learned policy at the start cell,
in the hallway and at the junction (memoryless agents), for variants of a configuration.

    python benchmarks/tmaze_diagnose.py --env tmaze_10 --seeds 10 --steps 1000000
"""

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from pobax.agent import TrainConfig, train
from pobax.env import TMaze, TMazeState


def probe(model, seed, length, observability):
    env = TMaze(length=length, observability=observability)
    m = jax.tree.map(lambda x: x[seed] if isinstance(x, jax.Array) and x.ndim > 0 else x, model)
    out = []
    for pos in (0, length // 2, length + 1):
        obs = env.observe(TMazeState(jnp.int32(pos), jnp.bool_(True)))
        _, d, v = m(None, obs[None], jnp.array([True]))
        out.append(f"pos {pos:2d}: p(u,r,d,l)={np.round(np.exp(np.asarray(d.logits[0])), 2)} V={float(v[0, 0]):.2f}")
    return " | ".join(out)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="tmaze_10")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--steps", type=int, default=1_000_000)
    p.add_argument("--variants", nargs="+", default=["full", "full:anneal_lr=False", "full:entropy_coeff=0.05"])
    args = p.parse_args()
    length = int(args.env.split("_")[1])
    for variant in args.variants:
        obs, *kvs = variant.split(":")
        memory = "memoryless"
        cfg = TrainConfig(env=args.env, observability=obs, memory=memory, hidden_size=32, num_envs=4,
                          total_steps=args.steps, num_seeds=args.seeds, lr=(2.5e-4,), lambda0=(0.5,), num_chunks=4)
        for kv in kvs:
            k, v = kv.split("=")
            cur = getattr(cfg, k)
            val = (float(v),) if isinstance(cur, tuple) else (v == "True" if isinstance(cur, bool) else type(cur)(v))
            if k == "memory":
                val = v
            cfg = dataclasses.replace(cfg, **{k: val})
        if cfg.memory != "memoryless":
            cfg = dataclasses.replace(cfg, action_concat=True, lr=(2.5e-3,), lambda0=(0.7,))
        r = train(cfg, save=False, progress=False)
        s = r.summary["sets"][0]["disc_return"]
        print(f"== {variant}: mean {s['mean']:.3f} [{s['ci_low']:.3f}, {s['ci_high']:.3f}]  ({r.steps_per_s:,.0f} steps/s)")
        m = r.metrics
        for seed, g in m.groupby("seed"):
            g = g.sort_values("update")
            n = max(1, len(g) // 10)
            line = (f"  seed {seed}: final {s['per_seed'][seed]:.3f} len {g.ep_length.iloc[-n:].mean():7.1f} "
                    f"entropy {g.entropy.iloc[-n:].mean():.3f}")
            if cfg.memory == "memoryless":
                line += "  " + probe(r.state.model, seed, length, obs)
            print(line, flush=True)


if __name__ == "__main__":
    main()
