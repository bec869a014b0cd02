"""The Battleship ceiling: mean return of the probability-search policy over many episodes.

    python benchmarks/bench_battleship_oracle.py --episodes 2000 --batch 250 --samples 1024

Plays `--episodes` independent episodes of `battleship_{size}` (vmapped in batches of `--batch`, each batch
one compiled `while_loop`), and prints the mean return with a 95% confidence interval (normal approximation,
1.96 standard errors; the returns are bounded and there are thousands of them), the mean number of shots, how
the smallest effective sample size of the belief estimate and the shots at which no importance sample was
consistent (the policy's fallback), the wall time, and the uniformly
random legal policy's exact value for comparison. Episode keys are `fold_in(key(seed), episode)`, so a run
is reproducible and batches are independent of the batch size.
"""

import argparse
import json
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from pobax.env._battleship import Battleship
from pobax.env._battleship_oracle import ProbabilitySearch, play_episode


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=2000)
    p.add_argument("--batch", type=int, default=50, help="episodes per compiled, vmapped call")
    p.add_argument("--size", type=int, default=10)
    p.add_argument("--ships", type=int, nargs="+", default=[5, 4, 3, 2])
    p.add_argument("--samples", type=int, default=1024, help="importance samples per shot")
    p.add_argument("--betas", type=float, nargs="+", default=[0.0, 2.0],
                   help="the proposals' weights on covering unexplained hits (samples split between them)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None, help="also write the summary to this JSON file")
    p.add_argument("--resume", default=None,
                   help="JSON-lines file of finished batches: appended to as batches finish, and batches already "
                        "in it are not played again (episode keys depend only on --seed and the episode number)")
    args = p.parse_args()

    oracle = ProbabilitySearch(args.size, tuple(args.ships), args.samples, tuple(args.betas))
    base = jax.random.key(args.seed)

    @jax.jit
    def play(episode_ids):
        keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(episode_ids)
        return jax.vmap(lambda k: play_episode(oracle, key=k))(keys)

    finished = {}
    if args.resume and os.path.exists(args.resume):
        with open(args.resume) as f:
            for line in f:
                row = json.loads(line)
                if (row["seed"], row["samples"], row["betas"]) == (args.seed, args.samples, list(args.betas)):
                    finished[(row["start"], row["count"])] = row
    returns, shots, min_ess, failures = [], [], [], []
    t0 = time.perf_counter()
    for start in range(0, args.episodes, args.batch):
        count = min(args.batch, args.episodes - start)
        row = finished.get((start, count))
        if row is None:
            # A short last batch is padded (and its padding dropped) so that there is one compiled shape.
            out = jax.device_get(play(start + jnp.arange(args.batch) % count))
            row = dict(seed=args.seed, samples=args.samples, betas=list(args.betas), start=start, count=count,
                       returns=out.episode_return[:count].tolist(), shots=out.shots[:count].tolist(),
                       min_ess=out.min_ess[:count].tolist(), failures=out.failures[:count].tolist())
            if args.resume:
                with open(args.resume, "a") as f:
                    f.write(json.dumps(row) + "\n")
        returns.append(np.asarray(row["returns"]))
        shots.append(np.asarray(row["shots"]))
        min_ess.append(np.asarray(row["min_ess"]))
        failures.append(np.asarray(row["failures"]))
        done = start + count
        print(f"  {done:6d} episodes, running mean return {np.concatenate(returns).mean():.3f}, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    elapsed = time.perf_counter() - t0
    returns, shots, min_ess, failures = map(np.concatenate, (returns, shots, min_ess, failures))
    mean = float(returns.mean())
    half = 1.96 * float(returns.std(ddof=1)) / math.sqrt(len(returns))
    summary = dict(
        env=f"battleship_{args.size}",
        ship_lengths=list(args.ships),
        samples=args.samples,
        betas=list(args.betas),
        episodes=len(returns),
        mean_return=mean,
        ci95=[mean - half, mean + half],
        mean_shots=float(shots.mean()),
        min_ess=float(min_ess.min()),
        median_episode_min_ess=float(np.median(min_ess)),
        shots_without_consistent_sample=int(failures.sum()),
        random_policy_return=Battleship(args.size, tuple(args.ships)).random_policy_return(),
        seconds=elapsed,
        device=str(jax.devices()[0].device_kind),
        jax=jax.__version__,
    )
    print(f"probability search on battleship_{args.size}, ships {tuple(args.ships)}, "
          f"{args.samples} importance samples per shot (betas {tuple(args.betas)}), {len(returns)} episodes")
    print(f"  mean return {mean:.3f} +- {half:.3f} (95% CI [{mean - half:.3f}, {mean + half:.3f}]), "
          f"mean shots {summary['mean_shots']:.2f}")
    print(f"  effective sample size: smallest {summary['min_ess']:.1f}, median over episodes of the episode's "
          f"smallest {summary['median_episode_min_ess']:.1f}; shots with no consistent sample: "
          f"{summary['shots_without_consistent_sample']}")
    print(f"  random legal policy (exact): {summary['random_policy_return']:.3f}")
    print(f"  {elapsed:.1f} s on {summary['device']} / jax {summary['jax']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(summary, f, indent=2)


if __name__ == "__main__":
    main()
