"""Env-only throughput: random legal actions, auto-reset, `jax.lax.scan` over steps, vmap over envs.

    python benchmarks/bench_env.py --envs tmaze_10 rocksample_11_11 --num-envs 1 64 1024 --steps 1000

Prints one row per (environment, num_envs): env steps/s, compile seconds, device and JAX version.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp

import pobax.env as E
from pobax.agent._train import default_unroll


def random_action(env, obs, key):
    mask = E.action_mask(obs)
    space = env.action_space
    if isinstance(space, E.Discrete):
        return space.sample(key, mask)
    return space.sample(key)


def make_runner(env, num_envs: int, num_steps: int, unroll: int = 1):
    def run(key):
        keys = jax.random.split(key, num_envs)
        state, ts = jax.vmap(lambda k: env.reset(key=k))(keys)

        def body(carry, _):
            state, ts, key = carry
            key, k_act, k_step = jax.random.split(key, 3)
            actions = jax.vmap(lambda o, k: random_action(env, o, k))(ts.obs, jax.random.split(k_act, num_envs))
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(
                state, actions, jax.random.split(k_step, num_envs)
            )
            # Use the observation in the result, so that XLA cannot skip computing it.
            obs_sum = sum(jnp.sum(x.astype(jnp.float32)) for x in jax.tree.leaves(ts.obs))
            return (state, ts, key), ts.reward.sum() + 0.0 * obs_sum

        _, rewards = jax.lax.scan(body, (state, ts, key), None, length=num_steps, unroll=unroll)
        return rewards.sum()

    return jax.jit(run)


def bench(name: str, num_envs: int, num_steps: int, observability: str = "partial", unroll: int | None = None) -> dict:
    env = E.make(name, observability)
    unroll = default_unroll() if unroll is None else unroll
    run = make_runner(env, num_envs, num_steps, unroll)
    t0 = time.perf_counter()
    compiled = run.lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(jax.random.key(1)))  # warm-up
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(jax.random.key(2)))
    elapsed = time.perf_counter() - t0
    return dict(
        env=name,
        observability=observability,
        num_envs=num_envs,
        unroll=unroll,
        steps_per_s=num_envs * num_steps / elapsed,
        compile_s=compile_s,
        device=str(jax.devices()[0].device_kind),
        jax=jax.__version__,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["tmaze_10"])
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 64, 1024])
    p.add_argument("--steps", type=int, default=1000, help="steps per environment in the timed scan")
    p.add_argument("--observability", default="partial")
    p.add_argument("--unroll", type=int, nargs="+", default=[None],
                   help="unroll factors of the step loop (default: the training rollout's, 1 on CPU and 4 on GPU)")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = p.parse_args()
    rows = []
    print(f"{'env':28s} {'num_envs':>8s} {'unroll':>6s} {'steps/s':>14s} {'compile s':>10s}  device / jax")
    for name in args.envs:
        for n in args.num_envs:
            for u in args.unroll:
                r = bench(name, n, args.steps, args.observability, u)
                rows.append(r)
                print(f"{name:28s} {n:8d} {r['unroll']:6d} {r['steps_per_s']:14,.0f} {r['compile_s']:10.2f}  "
                      f"{r['device']} / jax {r['jax']}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
