"""Env-only throughput: random legal actions, auto-reset, `jax.lax.scan` over steps, vmap over envs.

    python benchmarks/bench_env.py --envs tmaze_10 rocksample_11_11 --num-envs 1 64 1024 --steps 1000
    python benchmarks/bench_env.py --num-envs 8192 --unroll 1 4 8 --harness lean per_env --repeats 3   # on a GPU
    python benchmarks/bench_env.py --envs battleship_10 --num-envs 1 32 8192 --backend loop_free_placements=false

Prints one row per (environment, num_envs, unroll, harness): env steps/s (the fastest of `--repeats` timed runs),
compile seconds, the kernels (fusions and custom calls) of the optimised program, device and JAX version. The
harness (how actions are drawn and results kept) is `make_runner`'s. The environment is configured for the devices as
training configures it (`pobax.env._wrappers.for_backend` with `pobax._backend.Backend.of()`); `--backend NAME=VALUE`
replaces one of the platform's choices there, e.g. `loop_free_placements=false` (the Battleship reset's rejection
loop) or `reset_pool_size=none` (every environment's reset computed at every step).
"""

import argparse
import json
import re
import time

import jax
import jax.numpy as jnp

from pobax._cli.args import ScriptParser
import pobax.env as E
from pobax._backend import Backend, parse_overrides
from pobax.env._wrappers import for_backend


def random_action(env, obs, key):
    """One environment's random legal action."""
    mask = E.action_mask(obs)
    space = env.action_space
    if isinstance(space, E.Discrete):
        return space.sample(key, mask)
    return space.sample(key)


def random_actions(env, obs, key, num_envs: int):
    """Random legal actions of `num_envs` environments from one key (the same distribution as `random_action` for
    each): uniform over the allowed actions where the observation carries an action mask."""
    space = env.action_space
    if not isinstance(space, E.Discrete):
        return jax.vmap(space.sample)(jax.random.split(key, num_envs))
    mask = E.action_mask(obs)
    if mask is None:
        return jax.random.randint(key, (num_envs,), 0, space.n, dtype=jnp.int32)
    return jax.random.categorical(key, jnp.where(mask, 0.0, -jnp.inf), axis=-1).astype(jnp.int32)


HARNESSES = ("lean", "per_env")


def make_runner(env, num_envs: int, num_steps: int, unroll: int = 1, harness: str = "lean"):
    """The timed program: `num_steps` steps of `num_envs` environments (vmapped), with auto-reset.

    Each step the environments get one key each (their `step` takes one). `harness`:
    - "lean" (default): the actions of all environments are drawn from one key; the reward and the observation are
      added element-wise into the loop's carry (the observation in its own dtype) and summed once after the loop, so
      that XLA computes every observation but the loop holds only the environment's work and the draws;
    - "per_env": one key per environment for its action, and the reward and observation summed and written out
      at every step (reductions and a per-step output: on a GPU, T-Maze's loop runs 12 kernels a step instead of 7).
      Measured in docs/performance.md.
    """
    if harness not in HARNESSES:
        raise ValueError(f"unknown harness {harness!r}: use one of {', '.join(HARNESSES)}")

    def run(key):
        state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(key, num_envs))

        def step(state, ts, key):
            key, k_act, k_step = jax.random.split(key, 3)
            if harness == "lean":
                actions = random_actions(env, ts.obs, k_act, num_envs)
            else:
                actions = jax.vmap(lambda o, k: random_action(env, o, k))(ts.obs, jax.random.split(k_act, num_envs))
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(
                state, actions, jax.random.split(k_step, num_envs)
            )
            return state, ts, key

        if harness == "per_env":
            def body(carry, _):
                state, ts, key = step(*carry)
                # Use the observation in the result, so that XLA cannot skip computing it.
                obs_sum = sum(jnp.sum(x.astype(jnp.float32)) for x in jax.tree.leaves(ts.obs))
                return (state, ts, key), ts.reward.sum() + 0.0 * obs_sum

            _, rewards = jax.lax.scan(body, (state, ts, key), None, length=num_steps, unroll=unroll)
            return rewards.sum()

        # Observations are accumulated in their own dtype (a wrapping sum for uint8 images: one byte read and written
        # per pixel), booleans as uint8.
        acc_dtype = lambda x: jnp.uint8 if x.dtype == jnp.bool_ else x.dtype  # noqa: E731
        acc = (jnp.zeros(num_envs, jnp.float32), jax.tree.map(lambda x: jnp.zeros(x.shape, acc_dtype(x)), ts.obs))

        def body(carry, _):
            *carry, (r_acc, o_acc) = carry
            state, ts, key = step(*carry)
            o_acc = jax.tree.map(lambda a, x: a + x.astype(a.dtype), o_acc, ts.obs)
            return (state, ts, key, (r_acc + ts.reward, o_acc)), None

        (*_, (r_acc, o_acc)), _ = jax.lax.scan(body, (state, ts, key, acc), None, length=num_steps, unroll=unroll)
        return r_acc.sum() + 0.0 * sum(jnp.sum(x.astype(jnp.float32)) for x in jax.tree.leaves(o_acc))

    return jax.jit(run)


def bench(name: str, num_envs: int, num_steps: int, observability: str = "partial", unroll: int | None = None,
          harness: str = "lean", repeats: int = 1, backend: Backend | None = None) -> dict:
    """One row; `backend`: the implementation choices (default: the default devices' platform's)."""
    backend = Backend.of() if backend is None else backend
    env = for_backend(E.make(name, observability), backend)
    unroll = backend.scan_unroll() if unroll is None else unroll
    run = make_runner(env, num_envs, num_steps, unroll, harness)
    t0 = time.perf_counter()
    compiled = run.lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - t0
    kernels = len(re.findall(r"^\s*\S+ = .*\b(?:fusion|custom-call)\(", compiled.as_text(), re.M))
    jax.block_until_ready(compiled(jax.random.key(1)))  # warm-up
    elapsed = float("inf")
    for r in range(repeats):  # the fastest of `repeats` timed runs
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.key(2 + r)))
        elapsed = min(elapsed, time.perf_counter() - t0)
    return dict(
        env=name,
        observability=observability,
        num_envs=num_envs,
        unroll=unroll,
        harness=harness,
        steps_per_s=num_envs * num_steps / elapsed,
        compile_s=compile_s,
        kernels=kernels,
        device=str(jax.devices()[0].device_kind),
        jax=jax.__version__,
    )


def main():
    p = ScriptParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["tmaze_10"])
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 64, 1024])
    p.add_argument("--steps", type=int, default=1000, help="steps per environment in the timed scan")
    p.add_argument("--observability", default="partial")
    p.add_argument("--unroll", type=int, nargs="+", default=[None],
                   help="unroll factors of the step loop (default: the training rollout's, 1 on CPU and 4 on GPU)")
    p.add_argument("--harness", nargs="+", default=["lean"], choices=HARNESSES,
                   help="how actions are drawn and results kept (see make_runner); default lean")
    p.add_argument("--repeats", type=int, default=1, help="timed runs per row; the fastest counts")
    p.add_argument("--backend", nargs="+", default=[], metavar="NAME=VALUE",
                   help="replace choices of pobax/_backend.py, e.g. loop_free_placements=false")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = p.parse_args()
    try:
        choices = parse_overrides(",".join(args.backend))
    except ValueError as e:
        raise SystemExit(f"--backend: {e}") from None
    backend = Backend.of(None, choices)
    rows = []
    print(f"{'env':28s} {'num_envs':>8s} {'unroll':>6s} {'harness':>8s} {'steps/s':>14s} {'compile s':>10s} "
          f"{'kernels':>7s}  device / jax")
    for name in args.envs:
        for n in args.num_envs:
            for u in args.unroll:
                for h in args.harness:
                    r = bench(name, n, args.steps, args.observability, u, h, args.repeats, backend)
                    r["backend"] = {k: v for k, v in choices.items()}
                    rows.append(r)
                    print(f"{name:28s} {n:8d} {r['unroll']:6d} {h:>8s} {r['steps_per_s']:14,.0f} "
                          f"{r['compile_s']:10.2f} {r['kernels']:7d}  {r['device']} / jax {r['jax']}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
