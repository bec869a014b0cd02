"""Every registered environment trains with every agent: a few PPO updates each, and every part of the network
learns from that environment's observations (each weight array of the encoder, the memory, the actor and the critics
moves away from its initialisation in every run), with finite losses.

Tiny sizes keep it compile-dominated; learning itself is tested elsewhere.
"""

import equinox as eqx
import jax
import numpy as np
import pytest

from pobax.agent import Runs, TrainConfig
from pobax.eval import train

ENVS = ["tmaze_10", "rocksample_11_11", "battleship_10", "Navix-DMLab-Maze-01-v0"]
AGENTS = {
    "memoryless": dict(memory="memoryless"),
    "gru": dict(memory="gru", action_concat=True),
    "trxl": dict(memory="trxl", action_concat=True, embed_size=16, num_heads=2, qkv_features=16, window_mem=8,
                 window_grad=8),
    "ld": dict(memory="gru", action_concat=True, double_critic=True, ld_weight=(0.5,), lambda1=(0.5,)),
}


def unchanged_weights(before, after) -> list[str]:
    """Paths of the weight arrays that are equal before and after in some run (leading axis: the runs)."""
    flat_b = jax.tree_util.tree_leaves_with_path(eqx.filter(before, eqx.is_inexact_array))
    flat_a = jax.tree_util.tree_leaves(eqx.filter(after, eqx.is_inexact_array))
    return [jax.tree_util.keystr(path) for (path, b), a in zip(flat_b, flat_a)
            if (np.asarray(b) == np.asarray(a)).reshape(len(b), -1).all(1).any()]


def smoke(env: str, agent: dict, observability: str = "partial"):
    cfg = TrainConfig(env=env, observability=observability, hidden_size=16, num_envs=2, num_minibatches=2,
                      num_steps=16, total_steps=2 * 16 * 2, num_seeds=2, num_chunks=1, fast_compile=True, **agent)
    r = train(cfg, save=False, progress=False)
    m = r.metrics
    assert len(m) == 2 * 2 and sorted(m.env_step.unique()) == [32, 64]
    for col in ("pg_loss", "v_loss", "entropy", "approx_kl"):
        assert np.isfinite(m[col]).all(), (env, agent, col)
    assert unchanged_weights(Runs(cfg).init().model, r.state.model) == []


# By default `memoryless` on T-Maze (each environment's own tests step it); every other environment and agent (up to a
# minute's compile each on 2 CPU cores) with -m slow.
@pytest.mark.parametrize("env, agent", [
    (env, agent) if (agent, env) == ("memoryless", "tmaze_10") else
    pytest.param(env, agent, marks=pytest.mark.slow) for agent in AGENTS for env in ENVS])
def test_every_env_trains_every_part_of_every_agent(env, agent):
    smoke(env, AGENTS[agent])


# The continuous-action path (a Brax compile of a minute or more each on 2 CPU cores): -m slow.
@pytest.mark.slow
@pytest.mark.parametrize("agent", ["gru", "ld"])
def test_masked_mujoco_trains_with_continuous_actions(agent):
    smoke("Walker-V-v0", AGENTS[agent])
