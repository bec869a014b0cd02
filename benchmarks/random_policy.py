"""Returns of the uniformly random policy: the level at which an agent has learned nothing.

    python benchmarks/random_policy.py --envs Navix-DMLab-Maze-01-v0 Navix-DMLab-Maze-02-v0
    python benchmarks/random_policy.py --envs tmaze_10 --num-envs 512 --steps 4000 --json random.json

Each environment (registry settings, time limit and auto-reset included) runs `--num-envs` copies for `--steps`
steps with actions drawn uniformly from its action space (action masks, as Battleship's, are not used). Printed: the undiscounted and discounted return of the
episodes that ended, mean and 95% bootstrap CI over 10 groups of environments. Like the training logs' returns, the
mean is over finished episodes, so short episodes weigh a little more than in a fixed number of episodes per copy.
"""

import argparse
import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

import pobax
from pobax.eval._stats import bootstrap_ci


def random_policy(name: str, num_envs: int, steps: int, seed: int = 0) -> dict:
    env = pobax.env.make(name, "partial")
    gamma = env.gamma

    def run(key):
        k_reset, k_run = jax.random.split(key)
        state, _ = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_reset, num_envs))
        zeros = jnp.zeros(num_envs)

        def step(carry, k):
            state, ret, disc, discount, sums = carry
            k_act, k_env = jax.random.split(k)
            action = jax.vmap(env.action_space.sample)(jax.random.split(k_act, num_envs))
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, action, jax.random.split(k_env, num_envs))
            ret, disc = ret + ts.reward, disc + discount * ts.reward
            done = ts.done
            sums = (sums[0] + done, sums[1] + jnp.where(done, ret, 0.0), sums[2] + jnp.where(done, disc, 0.0))
            return (state, ret * ~done, disc * ~done, jnp.where(done, 1.0, discount * gamma), sums), None

        carry = (state, zeros, zeros, jnp.ones(num_envs), (zeros, zeros, zeros))
        carry, _ = jax.lax.scan(step, carry, jax.random.split(k_run, steps))
        return carry[-1]

    episodes, ret, disc = (np.asarray(x) for x in jax.jit(run)(jax.random.key(seed)))
    groups = np.array_split(np.arange(num_envs), 10)
    out = {"env": name, "num_envs": num_envs, "steps": steps, "episodes": int(episodes.sum()), "gamma": float(gamma)}
    for key, total in (("return", ret), ("disc_return", disc)):
        per_group = [total[g].sum() / max(episodes[g].sum(), 1) for g in groups]
        mean, lo, hi = bootstrap_ci(np.asarray(per_group))
        out[key] = {"mean": float(mean), "ci_low": float(lo), "ci_high": float(hi)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", nargs="+", required=True, help="environment IDs (see `pobax envs`)")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=12000, help="steps per copy (several times the time limit)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="also write the figures here")
    a = p.parse_args(argv)
    print(f"device: {jax.devices()[0].device_kind}, JAX {jax.__version__}")
    rows = []
    for name in a.envs:
        try:
            r = random_policy(name, a.num_envs, a.steps, a.seed)
        except (KeyError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        rows.append(r)
        d, u = r["disc_return"], r["return"]
        print(f"{name}: {r['episodes']} episodes | discounted {d['mean']:.4g} [{d['ci_low']:.4g}, {d['ci_high']:.4g}]"
              f" | undiscounted {u['mean']:.4g} [{u['ci_low']:.4g}, {u['ci_high']:.4g}]")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"command": "python benchmarks/random_policy.py " + " ".join(sys.argv[1:] if argv is None else argv),
                       "device": str(jax.devices()[0].device_kind), "jax": jax.__version__, "results": rows}, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
