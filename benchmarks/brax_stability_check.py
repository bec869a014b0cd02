"""Do the Brax robots stay finite under random actions? For each ID and physics setting, runs N envs × T
steps of uniform random actions (no resets) and prints the fraction of environments whose observation or
reward became non-finite, with the env steps/s of the timed run.

    python benchmarks/brax_stability_check.py --envs HalfCheetah-V-v0 --physics mjx-newton-1-4-damp mjx
"""

import argparse
import time

import jax
import jax.numpy as jnp

import pobax.env as E


def check(name: str, physics: str | None, n: int, t: int) -> tuple[float, float, float]:
    env = E.make(name, wrappers=False, **({} if physics is None else {"physics": physics}))

    @jax.jit
    def run(key):
        state, _ = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(key, n))

        def step(c, k):
            state, bad = c
            a = jax.random.uniform(k, (n,) + env.action_space.shape, minval=-1.0, maxval=1.0)
            state, ts = jax.vmap(lambda s, a: env.step(s, a, key=k))(state, a)
            return (state, bad | ~jnp.isfinite(ts.obs).all(axis=-1) | ~jnp.isfinite(ts.reward)), None

        (_, bad), _ = jax.lax.scan(step, (state, jnp.zeros((n,), bool)), jax.random.split(key, t))
        return bad.mean()

    t0 = time.perf_counter()
    jax.block_until_ready(run.lower(jax.random.key(0)).compile())
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    frac = float(run(jax.random.key(1)))
    return frac, n * t / (time.perf_counter() - t0), compile_s


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["Walker-V-v0", "HalfCheetah-V-v0", "Ant-V-v0", "Hopper-V-v0"])
    p.add_argument("--physics", nargs="+", default=["pinned"], help="settings of pobax.env.PHYSICS, or 'pinned'")
    p.add_argument("--num-envs", type=int, default=1024)
    p.add_argument("--steps", type=int, default=3000)
    a = p.parse_args()
    print(f"{a.num_envs} envs × {a.steps} random-action steps, {jax.devices()[0].device_kind}, jax {jax.__version__}")
    for name in a.envs:
        for ph in a.physics:
            frac, sps, comp = check(name, None if ph == "pinned" else ph, a.num_envs, a.steps)
            print(f"{name:20s} {ph:22s} non-finite envs {frac:.4f}   {sps:12,.0f} steps/s  compile {comp:5.1f} s",
                  flush=True)


if __name__ == "__main__":
    main()
