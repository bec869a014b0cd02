"""No-inventory Crafter (`craftax_pixels`): environment-only steps per second.

Compares the family's `AutoReset(pool_size=P)` (new worlds generated only for done environments, P at a time) with the
naive `AutoReset` (a world generated for every environment on every step, as Craftax's own auto-reset does),
on the registry's full wrapper stack with uniformly random actions, `num_steps` steps in one `lax.scan`.
Reports compile time, steps/s (environment steps summed over the batch), episode ends seen, device and
versions.

    JAX_PLATFORMS=cpu python benchmarks/bench_craftax.py                  # 1 and 64 envs (CPU default)
    python benchmarks/bench_craftax.py --num-envs 1024 4096 --pool-size 32  # on a GPU

`--max-timesteps` shortens Craftax's episodes (default: Craftax's own 100000) to measure the reset cost
with many episode ends; a random agent dies after ~O(100) steps anyway.
"""

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp

import pobax
from pobax.env import AutoReset


def make_runner(env, num_envs: int, num_steps: int):
    def run(key):
        k_reset, k_steps = jax.random.split(key)
        state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_reset, num_envs))

        def body(carry, k):
            state, n_done = carry
            k_act, k_env = jax.random.split(k)
            action = jax.random.randint(k_act, (num_envs,), 0, env.action_space.n)
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, action, jax.random.split(k_env, num_envs))
            return (state, n_done + jnp.sum(ts.done.astype(jnp.int32))), None

        (state, n_done), _ = jax.lax.scan(body, (state, jnp.zeros((), jnp.int32)), jax.random.split(k_steps, num_steps))
        return n_done

    return jax.jit(run)


def bench(reset: str, num_envs: int, num_steps: int, pool_size: int, max_timesteps: int | None, repeats: int):
    overrides = {} if max_timesteps is None else dict(max_timesteps=max_timesteps)
    inner = pobax.env.make("craftax_pixels", "partial", wrappers=False, **overrides)
    from pobax.env import TimeLimit

    inner = TimeLimit(inner, pobax.env.spec("craftax_pixels").family.max_steps)
    env = AutoReset(inner, pool_size=pool_size if reset == "pool" else None)
    run = make_runner(env, num_envs, num_steps)
    t0 = time.perf_counter()
    n_done = int(run(jax.random.key(0)))  # compile + first run
    first = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        n_done = int(jax.block_until_ready(run(jax.random.key(i + 1))))
        times.append(time.perf_counter() - t0)
    best = min(times)
    return dict(
        reset=reset, num_envs=num_envs, num_steps=num_steps, pool_size=pool_size if reset == "pool" else None,
        max_timesteps=max_timesteps, compile_and_first_run_s=round(first, 2), run_s=round(best, 3),
        steps_per_s=round(num_envs * num_steps / best, 1), episode_ends=n_done,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--num-envs", type=int, nargs="+", default=[1, 64])
    p.add_argument("--num-steps", type=int, default=64)
    p.add_argument("--pool-size", type=int, default=8)
    p.add_argument("--max-timesteps", type=int, default=None)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--resets", nargs="+", default=["pool", "naive"], choices=["pool", "naive"])
    args = p.parse_args()
    import craftax  # noqa: F401
    import importlib.metadata as md

    print(json.dumps(dict(device=str(jax.devices()[0]), platform=jax.default_backend(), jax=jax.__version__,
                          craftax=md.version("craftax"), python=platform.python_version())), flush=True)
    for n in args.num_envs:
        for reset in args.resets:
            r = bench(reset, n, args.num_steps, args.pool_size, args.max_timesteps, args.repeats)
            print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
