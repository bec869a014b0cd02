"""Masked MuJoCo throughput per robot and physics setting (Brax backend / MJX solver settings).

    JAX_PLATFORMS=cpu python benchmarks/bench_brax_backends.py --robots Walker HalfCheetah \\
        --physics mjx mjx-newton-1-4 positional --num-envs 1 64 1024 --steps 100

Each row runs the environment as `make` builds it (`AutoReset(TimeLimit(BraxEnv, 1000))`, the `-V-` mask)
under one physics setting: random actions, `jax.lax.scan` over `--steps` steps, `vmap` over `--num-envs`.
Prints env steps/s and compile seconds (lowering + XLA compile of the whole scan), plus the mean reward per
step and the fraction of steps that end an episode, so that a setting that changes the dynamics (or blows up
into NaNs) shows. Runs unchanged on GPU (drop `JAX_PLATFORMS=cpu`). `--json out.json` keeps the rows.
"""

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_env import random_action  # noqa: E402

from pobax.env import AutoReset, TimeLimit  # noqa: E402
from pobax.env._brax import PHYSICS, PHYSICS_BY_ROBOT, ROBOTS, BraxEnv  # noqa: E402


def make_runner(env, num_envs: int, num_steps: int):
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
            return (state, ts, key), (ts.reward.mean(), ts.done.mean(), jnp.isnan(ts.obs).any())

        _, (reward, done, nan) = jax.lax.scan(body, (state, ts, key), None, length=num_steps)
        return reward.mean(), done.mean(), nan.any()

    return jax.jit(run)


def bench(robot: str, physics: str, num_envs: int, num_steps: int, mask: str = "V") -> dict:
    env = AutoReset(TimeLimit(BraxEnv(robot, mask, physics=physics), 1000))
    run = make_runner(env, num_envs, num_steps)
    with jax.numpy_rank_promotion("allow"):
        t0 = time.perf_counter()
        compiled = run.lower(jax.random.key(0)).compile()
        compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(jax.random.key(1)))  # warm-up
    t0 = time.perf_counter()
    reward, done, nan = jax.block_until_ready(compiled(jax.random.key(2)))
    elapsed = time.perf_counter() - t0
    return dict(
        robot=robot,
        physics=physics,
        pinned=PHYSICS_BY_ROBOT[robot] == physics,
        num_envs=num_envs,
        steps=num_steps,
        steps_per_s=num_envs * num_steps / elapsed,
        compile_s=compile_s,
        mean_reward=float(reward),
        done_frac=float(done),
        nan=bool(nan),
        device=str(jax.devices()[0].device_kind),
        jax=jax.__version__,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", nargs="+", default=list(ROBOTS), choices=list(ROBOTS))
    p.add_argument("--physics", nargs="+", default=["mjx", "mjx-newton-1-4"], choices=list(PHYSICS))
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 64, 1024])
    p.add_argument("--steps", type=int, default=100, help="steps per environment in the timed scan")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = p.parse_args()
    rows = []
    print(
        f"{'robot':12s} {'physics':20s} {'num_envs':>8s} {'steps/s':>12s} {'compile s':>10s} "
        f"{'rew/step':>9s} {'done':>6s}  device / jax",
        flush=True,
    )
    for robot in args.robots:
        for physics in args.physics:
            for n in args.num_envs:
                r = bench(robot, physics, n, args.steps)
                rows.append(r)
                flag = " NaN!" if r["nan"] else ""
                pin = "*" if r["pinned"] else " "
                print(
                    f"{robot:12s} {physics + pin:20s} {n:8d} {r['steps_per_s']:12,.0f} {r['compile_s']:10.2f} "
                    f"{r['mean_reward']:9.3f} {r['done_frac']:6.3f}  {r['device']} / jax {r['jax']}{flag}",
                    flush=True,
                )
                if args.json:  # rewrite after every row: a long sweep that is cut short keeps what it measured
                    with open(args.json, "w") as f:
                        json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
