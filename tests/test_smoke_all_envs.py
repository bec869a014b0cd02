"""Every registered environment trains with every agent: a few PPO updates each, finite losses and returns.

Tiny sizes keep this a smoke test (compile-dominated); learning is tested elsewhere.
"""

import numpy as np
import pytest

from pobax.agent import TrainConfig
from pobax.eval import train

ENVS = ["tmaze_10", "rocksample_11_11", "battleship_10", "Navix-DMLab-Maze-01-v0"]
AGENTS = {
    "memoryless": dict(memory="memoryless"),
    "gru": dict(memory="gru", action_concat=True),
    "trxl": dict(memory="trxl", action_concat=True, embed_size=16, num_heads=2, qkv_features=16, window_mem=8,
                 window_grad=8),
    "ld": dict(memory="gru", action_concat=True, double_critic=True, ld_weight=(0.5,), lambda1=(0.5,)),
}


def smoke(env: str, agent: dict, observability: str = "partial"):
    cfg = TrainConfig(env=env, observability=observability, hidden_size=16, num_envs=2, num_minibatches=2,
                      num_steps=16, total_steps=2 * 16 * 2, num_seeds=2, num_chunks=1, **agent)
    r = train(cfg, save=False, progress=False)
    m = r.metrics
    assert len(m) == 2 * 2
    for col in ("pg_loss", "v_loss", "entropy", "approx_kl"):
        assert np.isfinite(m[col]).all(), (env, agent, col)
    if "lambda_discrepancy" in m:
        assert np.isfinite(m.lambda_discrepancy).all()


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("agent", list(AGENTS))
def test_every_env_trains_with_every_agent(env, agent):
    smoke(env, AGENTS[agent])


# `ld` (a GRU with two critics) covers the GRU's continuous-action path too; `gru` alone runs with -m slow
# (each is a ~80 s Brax compile on 2 CPU cores).
@pytest.mark.parametrize("agent", [pytest.param("gru", marks=pytest.mark.slow), "ld"])
def test_masked_mujoco_trains_with_continuous_actions(agent):
    smoke("Walker-V-v0", AGENTS[agent])
