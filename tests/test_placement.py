"""The devices a training program takes when none are named: as many as its environments fill
(`pobax._placement.default_devices`, docs/performance.md "Several devices"), and one job per GPU for `benchmark`."""

import json
import os
import subprocess
import sys
import textwrap
from types import SimpleNamespace

from pobax._placement import MIN_ENVS_PER_DEVICE, default_devices
from pobax.eval._parallel import default_jobs

FOUR = ["d0", "d1", "d2", "d3"]


def test_small_programs_take_one_device_large_ones_every_device():
    # The cases of the several-GPU table: T-Maze 30 seeds (30 × 4 environments) was slower on 2 and 4 GPUs than on
    # one; T-Maze's grid (120 × 4), Battleship's grid (120 × 32) and Craftax's Transformer-XL (3 × 256) were faster.
    assert default_devices(30, 4, FOUR) == ["d0"]
    assert default_devices(120, 4, FOUR) == FOUR
    assert default_devices(120, 32, FOUR) == FOUR
    assert default_devices(3, 256, FOUR) == FOUR
    # in between: as many devices as keep the threshold's environments on each, never none
    assert default_devices(1, 2 * MIN_ENVS_PER_DEVICE, FOUR) == ["d0", "d1"]
    assert default_devices(1, 1, FOUR) == ["d0"]
    assert default_devices(10_000, 64, ["d0"]) == ["d0"]
    # pixel MuJoCo's programs stay on one device: sharded over two GPUs, XLA's compiler crashes
    from pobax.env import spec

    assert default_devices(30, 16, FOUR, single_device=True) == ["d0"]
    assert spec("ant_pixels").single_device and spec("halfcheetah_pixels").single_device
    assert not any(spec(e).single_device for e in ("tmaze_10", "battleship_10", "craftax_pixels", "Walker-V-v0"))


def test_benchmark_runs_one_job_per_gpu():
    gpus = [SimpleNamespace(platform="gpu") for _ in range(4)]
    env = dict(os.environ)
    try:
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"  # as the command line sets it
        assert default_jobs(gpus) == 4
        assert default_jobs(gpus[:1]) == 1
        assert default_jobs([SimpleNamespace(platform="cpu") for _ in range(4)]) == 1
    finally:
        os.environ.clear()
        os.environ.update(env)


SCRIPT = textwrap.dedent("""
    import json, jax
    from pobax.agent import Runs, TrainConfig
    small = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_seeds=30)
    grid = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_seeds=5,
                       lr=(2.5e-3, 2.5e-4, 2.5e-5, 2.5e-6), lambda0=(0.1, 0.3, 0.5, 0.7, 0.9, 0.95))
    count = lambda runs: 1 if runs.mesh is None else runs.mesh.devices.size
    print(json.dumps({"small": count(Runs(small)), "grid": count(Runs(grid)),
                      "named": count(Runs(small, jax.devices()[:2]))}))
""")


def test_train_and_sweep_default_to_the_devices_their_runs_fill():
    """On four forced CPU devices, `Runs` (what train, sweep and gap build) shards T-Maze's 30 seeds over one device,
    its sweep grid over all four, and named devices over exactly those."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=4")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"small": 1, "grid": 4, "named": 2}
