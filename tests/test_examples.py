"""The notebook-style examples (examples/NN_*.py) run, at their tiny size (`POBAX_EXAMPLE_TINY=1`), as a user would
run them, and what they print and write says what the example shows. (Other scripts in examples/ have their own
tests.)"""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("[0-9][0-9]_*.py"))


def check_environments(out: Path, stdout: str):
    # The hand-written T-Maze walk: nothing on the way, the goal's reward on the last step, which ends the episode.
    steps = re.findall(r"^action (\d): obs .*, reward ([-\d.]+), terminated (True|False)$", stdout, re.M)
    assert len(steps) == 7, stdout  # tmaze_5: 5 corridor cells, the junction, the turn
    assert all(r == "0.0" and t == "False" for _, r, t in steps[:-1]) and steps[-1][1:] == ("4.0", "True")
    # Observabilities of RockSample: after checking rock 0 `partial` and `perfect_memory` agree on it.
    rocks = dict(re.findall(r"^(partial|perfect_memory|full) +rock entries after checking rock 0: (.*)$", stdout, re.M))
    assert set(rocks) == {"partial", "perfect_memory", "full"} and rocks["partial"] == rocks["perfect_memory"]
    assert (out / "battleship_untrained.gif").exists()


def check_train_and_plot(out: Path, stdout: str):
    # Two sets (step sizes) × 2 seeds for the GRU, one set × 2 seeds for the floor, 4 updates of 2 envs × 16 steps.
    for name, sets in (("gru", 2), ("memoryless", 1)):
        (run,) = out.glob(f"tmaze5-{name}-*")
        m = pd.read_csv(run / "metrics.csv")
        assert len(m) == sets * 2 * 4 and sorted(m.hp_index.unique()) == list(range(sets))
        assert m.env_step.max() == 128
        assert f"{name}: best set lr=" in stdout and run.name in stdout
    assert len(list(out.glob("tmaze5-curves-*.png"))) == 1


def check_evaluate_and_render(out: Path, stdout: str):
    (run,) = out.glob("tmaze5-gru-*")
    episodes = pd.read_csv(run / "eval-partial-stochastic-seed0.csv")
    assert len(episodes) == 2 * 5  # 2 seeds × 5 episodes
    # T-Maze pays only on an episode's last step: the goal's 4 or the wrong arm's -0.1 if it ends there, 0 if it is
    # cut by the time limit; so discounted = return × γ^(length - 1), for every episode and the rendered one.
    ended = episodes[episodes.terminated]
    assert set(ended["return"].round(3)) <= {-0.1, 4.0} and (episodes[episodes.truncated]["return"] == 0).all()
    np.testing.assert_allclose(episodes.disc_return, episodes["return"] * 0.99 ** (episodes.length - 1),
                               rtol=1e-5, atol=1e-6)
    length, ret, disc = re.search(r"^(\d+) steps, return ([-\d.]+) \(discounted ([-\d.]+)\)", stdout, re.M).groups()
    assert float(disc) == pytest.approx(float(ret) * 0.99 ** (int(length) - 1), abs=2e-3)
    assert (out / "tmaze5-episode.png").exists()


CHECKS = {"01_environments.py": check_environments, "02_train_and_plot.py": check_train_and_plot,
          "03_evaluate_and_render.py": check_evaluate_and_render}


def test_every_example_is_checked():
    assert [p.name for p in EXAMPLES] == list(CHECKS)


@pytest.mark.slow
@pytest.mark.parametrize("script", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "POBAX_EXAMPLE_TINY": "1", "POBAX_EXAMPLE_OUT": str(out)}
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not (tmp_path / "runs").exists()  # everything went where POBAX_EXAMPLE_OUT said
    for gif in out.rglob("*.gif"):
        assert gif.with_suffix(".png").exists() and gif.stat().st_size > 1000
    CHECKS[script.name](out, proc.stdout)
