"""Masked MuJoCo per robot and physics setting (Brax backend / MJX solver settings): speed and fidelity.

    JAX_PLATFORMS=cpu python benchmarks/bench_brax_backends.py --robots Walker HalfCheetah \\
        --physics mjx mjx-newton-1-4 mjx-newton-1-4-damp positional --num-envs 1 64 1024 --steps 50
    JAX_PLATFORMS=cpu python benchmarks/bench_brax_backends.py --fidelity --robots Walker HalfCheetah Hopper \\
        --physics mjx mjx-newton-1-4 mjx-newton-1-4-damp

Timing: each row runs the environment as `make` builds it (`AutoReset(TimeLimit(BraxEnv, 1000))`, the `-V-`
mask) under one physics setting: random actions, `jax.lax.scan` over `--steps` steps, `vmap` over
`--num-envs`. The pinned setting of each robot is marked `*`. Prints env steps/s (wall time and process CPU
time), compile seconds (lowering + XLA compile of the whole scan), the mean reward per step and the fraction
of steps that end an episode, so that a setting that changes the dynamics (or blows up into NaNs) shows.

Fidelity (`--fidelity`): for the MJX settings, the mean one-step and five-step open-loop error of the
observation against Brax's MJX as shipped (`mjx`), in units of each entry's standard deviation.

Runs unchanged on GPU (drop `JAX_PLATFORMS=cpu`). `--json out.json` keeps the timing rows.
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
    """Compile and time one (robot, physics, num_envs) setting."""
    env = AutoReset(TimeLimit(BraxEnv(robot, mask, physics=physics), 1000))
    run = make_runner(env, num_envs, num_steps)
    t0 = time.perf_counter()
    compiled = run.lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(jax.random.key(1)))  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    reward, done, nan = jax.block_until_ready(compiled(jax.random.key(2)))
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    return dict(
        robot=robot,
        physics=physics,
        pinned=PHYSICS_BY_ROBOT[robot] == physics,
        num_envs=num_envs,
        steps=num_steps,
        steps_per_s=num_envs * num_steps / elapsed,
        # Steps per second of this process's CPU time (all threads): less sensitive than wall time to other
        # processes sharing the CPU; on GPU it measures the host's share only.
        steps_per_cpu_s=num_envs * num_steps / max(cpu, 1e-9),
        compile_s=compile_s,
        mean_reward=float(reward),
        done_frac=float(done),
        nan=bool(nan),
        device=str(jax.devices()[0].device_kind),
        jax=jax.__version__,
    )


def fidelity(robot: str, physics: list[str], reference: str = "mjx", num_envs: int = 64, num_steps: int = 50,
             horizon: int = 5) -> list[dict]:
    """How far each MJX setting's dynamics are from `reference` (Brax's MJX as shipped).

    States are sampled from a random-action rollout under `reference` (auto-reset, `num_envs` x `num_steps`).
    From each state, both settings run the same `horizon` random actions open loop; the error is the mean over
    observation entries of |obs - obs_reference| / std(obs_reference), after 1 step and after `horizon` steps.
    Only MJX settings can be compared (the other backends have other state types).
    """
    ref_env = BraxEnv(robot, "F", physics=reference)
    wrapped = AutoReset(TimeLimit(ref_env, 1000))

    @jax.jit
    def sample_states(key):
        state, ts = jax.vmap(lambda k: wrapped.reset(key=k))(jax.random.split(key, num_envs))

        def body(carry, key):
            state, ts = carry
            k_act, k_step = jax.random.split(key)
            a = jax.random.uniform(k_act, (num_envs,) + wrapped.action_space.shape, minval=-1.0, maxval=1.0)
            keys = jax.random.split(k_step, num_envs)
            state, ts = jax.vmap(lambda s, a, k: wrapped.step(s, a, key=k))(state, a, keys)
            return (state, ts), state.env_state

        _, states = jax.lax.scan(body, (state, ts), jax.random.split(key, num_steps))
        return jax.tree.map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), states)

    def open_loop(env):
        @jax.jit
        def run(states, actions):
            def one(state, acts):
                def body(s, a):
                    s, ts = env.step(s, a, key=jax.random.key(0))
                    return s, ts.obs
                return jax.lax.scan(body, state, acts)[1]
            return jax.vmap(one)(states, actions)
        return run

    states = sample_states(jax.random.key(0))
    n = num_envs * num_steps
    actions = jax.random.uniform(jax.random.key(1), (n, horizon) + ref_env.action_space.shape, minval=-1.0, maxval=1.0)
    ref = open_loop(ref_env)(states, actions)
    scale = jnp.std(ref.reshape(-1, ref.shape[-1]), axis=0) + 1e-6
    rows = []
    for name in physics:
        if PHYSICS[name].backend != "mjx":
            continue
        obs = open_loop(BraxEnv(robot, "F", physics=name))(states, actions)
        err = jnp.abs(obs - ref) / scale
        rows.append(dict(robot=robot, physics=name, reference=reference, horizon=horizon,
                         err_1=float(jnp.nanmean(err[:, 0])), err_h=float(jnp.nanmean(err[:, -1])),
                         nan=bool(jnp.isnan(obs).any())))
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", nargs="+", default=list(ROBOTS), choices=list(ROBOTS))
    p.add_argument("--physics", nargs="+", default=["mjx", "mjx-newton-1-4", "mjx-newton-1-4-damp"],
                   choices=list(PHYSICS))
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 64, 1024])
    p.add_argument("--steps", type=int, default=100, help="steps per environment in the timed scan")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    p.add_argument("--fidelity", action="store_true",
                   help="instead of timing, compare the MJX settings' dynamics with Brax's MJX as shipped")
    args = p.parse_args()
    if args.fidelity:
        print(f"{'robot':12s} {'physics':20s} {'err 1 step':>11s} {'err 5 steps':>12s}  (mean |obs - obs_mjx| / std)")
        for robot in args.robots:
            for r in fidelity(robot, args.physics):
                print(f"{robot:12s} {r['physics']:20s} {r['err_1']:11.4f} {r['err_h']:12.4f}"
                      f"{'  NaN!' if r['nan'] else ''}", flush=True)
        return
    rows = []
    print(
        f"{'robot':12s} {'physics':20s} {'num_envs':>8s} {'steps/s':>12s} {'steps/cpu-s':>12s} "
        f"{'compile s':>10s} {'rew/step':>9s} {'done':>6s}  device / jax",
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
                    f"{robot:12s} {physics + pin:20s} {n:8d} {r['steps_per_s']:12,.0f} "
                    f"{r['steps_per_cpu_s']:12,.0f} {r['compile_s']:10.2f} "
                    f"{r['mean_reward']:9.3f} {r['done_frac']:6.3f}  {r['device']} / jax {r['jax']}{flag}",
                    flush=True,
                )
                if args.json:  # rewrite after every row: a long sweep that is cut short keeps what it measured
                    with open(args.json, "w") as f:
                        json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
