"""Can the maze ceiling's network represent the shortest-path policy? Supervised imitation, no RL.

    python benchmarks/maze_imitation.py --mazes 01 02 --steps 1500
    python benchmarks/maze_imitation.py --mazes 02 --observability partial --steps 1500 --json imitation.json

States (start cell, direction, goal cell) are drawn as the environment's reset draws them; the target is the
shortest-path oracle's action (`pobax.env.MazeOracle`, the registry's reference). The network is the ceiling's,
`pobax.agent.ActorCritic` (memoryless, hidden 512, the observation flattened; the batch of states passes as one
sequence, which a memoryless network treats state by state), its actor trained by Adam on the cross-entropy at the
ceiling's step size. Printed: the accuracy on 4096 held-out states during training,
and the majority action's share. If the network reaches a high accuracy here while PPO leaves it at the random
policy's return, the representation is not what stops the ceiling.
"""

import argparse
import json
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from pobax.agent import ActorCritic
from pobax.env import MazeOracle
from pobax.env._dmlab_maze import DMLabMaze


def policy(model: ActorCritic, obs):
    """The actor's action distribution for a batch of observations (one sequence: no memory to carry)."""
    return model(None, obs, jnp.zeros(obs.shape[0], bool))[1]


def imitation(maze_id: str, observability: str, steps: int, batch: int, lr: float, hidden: int, seed: int) -> dict:
    env = DMLabMaze(maze_id, observability)
    oracle = MazeOracle(np.asarray(env.walls))

    def sample(key, n):
        states = jax.vmap(lambda k: env.reset(key=k)[0])(jax.random.split(key, n))
        return jax.vmap(env.observe)(states), jax.vmap(oracle)(states.position, states.direction, states.goal)

    key_model, key_test, key_train = jax.random.split(jax.random.key(seed), 3)
    x_test, y_test = sample(key_test, 4096)
    model = ActorCritic(env, key=key_model, memory="memoryless", hidden_size=hidden, encoder="flatten")
    opt = optax.adam(lr)
    opt_state = opt.init(eqx.filter(model, eqx.is_array))

    @eqx.filter_jit
    def train_step(model, opt_state, key):
        x, y = sample(key, batch)
        loss, grads = eqx.filter_value_and_grad(lambda m: -policy(m, x).log_prob(y).mean())(model)
        updates, opt_state = opt.update(grads, opt_state)
        return eqx.apply_updates(model, updates), opt_state, loss

    accuracy = eqx.filter_jit(lambda m: jnp.mean(policy(m, x_test).mode() == y_test))
    curve = []
    for i, k in enumerate(jax.random.split(key_train, steps), start=1):
        model, opt_state, loss = train_step(model, opt_state, k)
        if i % max(steps // 10, 1) == 0 or i == steps:
            curve.append({"step": i, "loss": float(loss), "test_accuracy": float(accuracy(model))})
            print(f"  maze {maze_id} {observability}: step {i} loss {float(loss):.3f} accuracy "
                  f"{curve[-1]['test_accuracy']:.3f}", flush=True)
    majority = float(np.bincount(np.asarray(y_test), minlength=3).max() / len(y_test))
    return {"maze": maze_id, "observability": observability, "obs_size": int(np.prod(x_test.shape[1:])),
            "steps": steps, "batch": batch, "lr": lr, "hidden": hidden, "majority_share": majority, "curve": curve}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mazes", nargs="+", default=["01", "02"], choices=["01", "02", "03"])
    p.add_argument("--observability", default="full", choices=["full", "partial"])
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=2.5e-4, help="the ceiling's step size (paper tables, mazes 01/02)")
    p.add_argument("--hidden", type=int, default=512)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="also write the figures here")
    a = p.parse_args(argv)
    print(f"device: {jax.devices()[0].device_kind}, JAX {jax.__version__}")
    rows = []
    for m in a.mazes:
        r = imitation(m, a.observability, a.steps, a.batch, a.lr, a.hidden, a.seed)
        rows.append(r)
        print(f"maze {m} ({a.observability}, {r['obs_size']} inputs): accuracy {r['curve'][-1]['test_accuracy']:.3f} "
              f"after {a.steps} steps; majority action {r['majority_share']:.3f}")
    if a.json:
        with open(a.json, "w") as f:
            args = sys.argv[1:] if argv is None else argv
            json.dump({"command": "python benchmarks/maze_imitation.py " + " ".join(args),
                       "device": str(jax.devices()[0].device_kind), "jax": jax.__version__, "results": rows}, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
