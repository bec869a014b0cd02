"""Reference values of the DMLab mazes: the shortest-path oracle, exactly and by rollouts.

    python benchmarks/bench_maze_oracle.py --mazes 01 02 03 --num-envs 1024 --episodes-per-env 16

For each maze, prints:
- the exact oracle value (mean discounted return and mean episode length over all (start, direction, goal)
  triples, start != goal, by numpy BFS) and how long the BFS took;
- the same quantities estimated by running the oracle policy (`pobax.env.MazeOracle`) in the registered
  environment (`make`, with time limit and auto-reset), over the first `--episodes-per-env` episodes of
  every environment, with a 95% confidence interval. The exact value must lie inside it;
- a uniform random policy (first episode of every environment, to the goal or the time limit), and the
  rollout throughput of both.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import pobax.env as E
from pobax.env._dmlab_maze import ORACLE_VALUES
from pobax.env._maze_oracle import oracle_values


def rollout(env, policy, num_envs: int, num_steps: int, episodes_per_env: int):
    """Discounted return and length of the first `episodes_per_env` episodes of each environment."""
    gamma = env.gamma

    def run(key):
        state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(key, num_envs))
        zeros = jnp.zeros((num_envs,), jnp.float32)
        count = jnp.zeros((num_envs,), jnp.int32)
        carry = (state, key, zeros, zeros, count, zeros, zeros)

        def body(carry, _):
            state, key, ret, length, count, ret_sum, len_sum = carry
            key, k_act, k_step = jax.random.split(key, 3)
            inner = state.env_state  # AutoReset(TimeLimit(maze)) -> TimeLimitState -> DMLabMazeState
            actions = jax.vmap(policy)(inner, jax.random.split(k_act, num_envs))
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(
                state, actions, jax.random.split(k_step, num_envs)
            )
            ret = ret + ts.reward * gamma**length
            length = length + 1
            record = ts.done & (count < episodes_per_env)
            ret_sum = ret_sum + jnp.where(record, ret, 0.0)
            len_sum = len_sum + jnp.where(record, length, 0.0)
            count = count + ts.done
            ret = jnp.where(ts.done, 0.0, ret)
            length = jnp.where(ts.done, 0.0, length)
            return (state, key, ret, length, count, ret_sum, len_sum), None

        (_, _, _, _, count, ret_sum, len_sum), _ = jax.lax.scan(body, carry, None, length=num_steps)
        return count, ret_sum, len_sum

    return jax.jit(run)


def summary(count, ret_sum, len_sum, episodes_per_env: int) -> dict:
    count, ret_sum, len_sum = (np.asarray(x, np.float64) for x in (count, ret_sum, len_sum))
    finished = np.minimum(count, episodes_per_env)
    # Per-environment means are i.i.d. across environments: a normal 95% interval over them.
    ok = finished > 0
    per_env = ret_sum[ok] / finished[ok]
    return dict(
        episodes=int(finished.sum()),
        all_finished=bool((count >= episodes_per_env).all()),
        discounted_return=float(ret_sum.sum() / max(finished.sum(), 1)),
        ci95=float(1.96 * per_env.std(ddof=1) / np.sqrt(len(per_env))) if len(per_env) > 1 else float("nan"),
        mean_length=float(len_sum.sum() / max(finished.sum(), 1)),
    )


def bench(maze_id: str, num_envs: int, episodes_per_env: int, seed: int) -> dict:
    name = f"Navix-DMLab-Maze-{maze_id}-v0"
    env = E.make(name)
    bare = env.unwrapped
    t0 = time.perf_counter()
    exact = oracle_values(np.asarray(bare.walls), bare.gamma)
    bfs_s = time.perf_counter() - t0
    oracle = E.MazeOracle(np.asarray(bare.walls))
    # Oracle episodes are at most a few hundred steps; 3x the mean per episode leaves a wide margin.
    num_steps = int(3 * episodes_per_env * exact["optimal_mean_episode_length"]) + 200
    # The random policy's first episode in each environment, run to the goal or the time limit.
    policies = {
        "oracle": (lambda s, k: oracle(s.position, s.direction, s.goal), num_steps, episodes_per_env),
        "random": (lambda s, k: jax.random.randint(k, (), 0, 3, dtype=jnp.int32), env.max_steps_in_episode, 1),
    }
    row = dict(env=name, num_envs=num_envs, exact=exact, stored=ORACLE_VALUES[maze_id], bfs_s=bfs_s)
    for label, (policy, num_steps, episodes_per_env) in policies.items():
        run = rollout(env, policy, num_envs, num_steps, episodes_per_env)
        compiled = run.lower(jax.random.key(seed)).compile()
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(jax.random.key(seed)))
        elapsed = time.perf_counter() - t0
        row[label] = dict(**summary(*out, episodes_per_env), steps_per_s=num_envs * num_steps / elapsed)
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mazes", nargs="+", default=["01", "02", "03"])
    p.add_argument("--num-envs", type=int, default=1024)
    p.add_argument("--episodes-per-env", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = p.parse_args()
    rows = []
    for maze_id in args.mazes:
        r = bench(maze_id, args.num_envs, args.episodes_per_env, args.seed)
        rows.append(r)
        o, rnd, ex = r["oracle"], r["random"], r["exact"]
        print(
            f"{r['env']}: exact oracle {ex['optimal_discounted_return']:.4f} "
            f"(mean {ex['optimal_mean_episode_length']:.1f} steps; BFS {r['bfs_s']:.1f} s) | "
            f"rollouts {o['discounted_return']:.4f} +- {o['ci95']:.4f} over {o['episodes']} episodes "
            f"(mean {o['mean_length']:.1f} steps, all finished: {o['all_finished']}, "
            f"{o['steps_per_s']:,.0f} steps/s) | "
            f"random policy {rnd['discounted_return']:.4f} +- {rnd['ci95']:.4f} over {rnd['episodes']} episodes "
            f"(mean {rnd['mean_length']:.0f} steps)",
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
