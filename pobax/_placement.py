"""The devices one training program uses when the caller names none.

A program's runs are sharded over devices, each device training its own runs (`pobax.agent.Runs`). That pays only
where each device gets enough work to hide its per-step latency: measured on four H100s (`docs/performance.md`,
"Several devices"), Battleship's sweep grid (120 runs × 32 environments) ran 3.56× faster on four GPUs and Craftax's
Transformer-XL (3 runs × 256 environments) 1.94×, T-Maze's grid (120 runs × 4 environments) 1.19×, while T-Maze's 30
seeds (30 runs × 4 environments) ran as fast on two GPUs as on one and 7% slower on four. So a program takes as many
of the available devices as keep at least `min_envs_per_device` environments on each, and at least one: T-Maze's 30
seeds train on one GPU, the grids and Craftax on four. Pixel MuJoCo's programs stay on one device
(`EnvSpec.single_device`: sharded, XLA's GPU compiler crashes). Naming the devices
(`--devices`, `train(..., devices=...)`) overrides this; a multi-process run always uses every device (each process
must take part).
"""

import jax

#: Environments stepped in parallel on each device below which a program gains nothing from another device.
MIN_ENVS_PER_DEVICE = 100


def default_devices(num_runs: int, num_envs: int, devices: list | None = None,
                    min_envs_per_device: int = MIN_ENVS_PER_DEVICE, single_device: bool = False) -> list:
    """The first n of `devices` (default: `jax.devices()`) for a program of `num_runs` runs of `num_envs`
    environments each: the most that keep `min_envs_per_device` environments on each device, at least one; one
    where the environment's programs cannot be sharded (`single_device`: `EnvSpec.single_device`); every device in
    a multi-process run."""
    devs = jax.devices() if devices is None else list(devices)
    if jax.process_count() > 1:
        return devs
    if single_device:
        return devs[:1]
    n = max(1, min(len(devs), (num_runs * num_envs) // min_envs_per_device))
    return devs[:n]
