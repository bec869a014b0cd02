"""One learning test small enough for CI (its slow suite): on T-Maze 3 the GRU agent beats the memoryless one."""

import pytest

from pobax.agent import TrainConfig
from pobax.eval import train


@pytest.mark.slow  # 40 s on 2 cores
def test_gru_beats_memoryless_on_tmaze_3():
    common = dict(env="tmaze_3", hidden_size=32, num_envs=4, num_steps=128, total_steps=100_000, num_seeds=3,
                  num_chunks=2)
    gru = train(TrainConfig(memory="gru", action_concat=True, lr=(2.5e-3,), lambda0=(0.7,), **common),
                save=False, progress=False)
    mlp = train(TrainConfig(memory="memoryless", lr=(2.5e-3,), lambda0=(0.3,), **common), save=False, progress=False)
    g = gru.summary["sets"][0]["disc_return"]
    m = mlp.summary["sets"][0]["disc_return"]
    optimal, memoryless_best = 4 * 0.99**4, 0.5 * 3.9 * 0.99**4
    # the memoryless agent cannot beat a coin flip at the junction; the GRU remembers the cue
    assert m["mean"] < memoryless_best + 0.05
    assert g["mean"] > memoryless_best + 0.5
    assert g["ci_low"] > m["ci_high"]
    assert g["mean"] < optimal + 1e-3
