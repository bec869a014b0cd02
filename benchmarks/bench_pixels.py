"""Pixel MuJoCo throughput: env-only steps/s (with and without rendering) and render-only frames/s.

    python benchmarks/bench_pixels.py --envs halfcheetah_pixels ant_pixels --num-envs 1 64 --steps 100
    python benchmarks/bench_pixels.py --num-envs 1024 4096 --steps 200          # on a GPU

Rows (one per environment, number of environments and mode):

- `step+render`: `env.step` of the `partial` observability (physics and a rendered frame), random actions,
  auto-reset, `lax.scan` over steps, vmap over environments (as training runs it);
- `step`: the same with the `full` observability (the identical physics, no rendering);
- `render`: the ray caster alone on fixed MJX data, vmapped over environments.

Each row has the throughput, the time per environment step or frame, and the compile seconds; the device
and JAX version are printed first. Options `--image-size`, `--supersample`, `--no-shadows` change the
renderer.
"""

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_env import make_runner  # noqa: E402

import pobax.env as E  # noqa: E402
from pobax.env._pixels import TORSO_BODY  # noqa: E402
from pobax.env._raycast import render  # noqa: E402


def _time(fn, *args) -> tuple[float, float]:
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))  # warm-up
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    return time.perf_counter() - t0, compile_s


def bench_steps(name: str, observability: str, num_envs: int, num_steps: int, **overrides) -> dict:
    env = E.make(name, observability, **overrides)
    run = make_runner(env, num_envs, num_steps)
    elapsed, compile_s = _time(run, jax.random.key(0))
    n = num_envs * num_steps
    mode = "step+render" if observability == "partial" else "step"
    return dict(env=name, mode=mode, num_envs=num_envs, per_s=round(n / elapsed, 1),
                us_each=round(1e6 * elapsed / n, 2), compile_s=round(compile_s, 2))


def bench_render(name: str, num_envs: int, num_frames: int, **overrides) -> dict:
    import mujoco
    import numpy as np

    env = E.make(name, "partial", wrappers=False, **overrides)
    scene = env.scene
    # Poses from MuJoCo's C library (initial pose plus joint noise per environment): no MJX compile needed.
    mj_model = env.brax.brax_env.sys.mj_model
    data, rng, poses = mujoco.MjData(mj_model), np.random.default_rng(0), []
    for _ in range(num_envs):
        data.qpos[:] = mj_model.qpos0 + 0.1 * rng.standard_normal(mj_model.nq)
        mujoco.mj_forward(mj_model, data)
        poses.append((data.geom_xpos.copy(), data.geom_xmat.reshape(-1, 3, 3).copy(), data.xpos[TORSO_BODY].copy()))
    xpos, xmat, torso = (jnp.asarray(np.stack(p), jnp.float32) for p in zip(*poses))

    @jax.jit
    def run(xpos, xmat, torso):
        def body(acc, i):
            # Move the torso target a little each frame so that no frame is reused.
            shift = jnp.stack([0.01 * i.astype(jnp.float32), jnp.float32(0.0), jnp.float32(0.0)])
            frames = jax.vmap(lambda p, m, t: render(scene, p, m, t))(xpos, xmat, torso + shift[None])
            return acc + jnp.sum(frames.astype(jnp.float32)), None

        acc, _ = jax.lax.scan(body, jnp.float32(0.0), jnp.arange(num_frames))
        return acc

    elapsed, compile_s = _time(run, xpos, xmat, torso)
    n = num_envs * num_frames
    return dict(env=name, mode="render", num_envs=num_envs, per_s=round(n / elapsed, 1),
                us_each=round(1e6 * elapsed / n, 2), compile_s=round(compile_s, 2))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["halfcheetah_pixels", "ant_pixels"])
    p.add_argument("--num-envs", nargs="+", type=int, default=[1, 64])
    p.add_argument("--steps", type=int, default=100, help="steps (or frames) per timed run")
    p.add_argument("--modes", nargs="+", default=["render", "step+render", "step"])
    p.add_argument("--image-size", type=int, default=32)
    p.add_argument("--supersample", type=int, default=1)
    p.add_argument("--no-shadows", action="store_true")
    p.add_argument("--json", action="store_true", help="one JSON object per row instead of a table")
    args = p.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}", flush=True)
    overrides = dict(image_size=args.image_size, supersample=args.supersample, shadows=not args.no_shadows)
    print(f"renderer: {overrides}", flush=True)
    if not args.json:
        print(f"{'env':<20} {'mode':<12} {'num_envs':>8} {'per_s':>12} {'us_each':>10} {'compile_s':>9}", flush=True)
    for name in args.envs:
        for n in args.num_envs:
            for mode in args.modes:
                if mode == "render":
                    row = bench_render(name, n, args.steps, **overrides)
                elif mode == "step+render":
                    row = bench_steps(name, "partial", n, args.steps, **overrides)
                else:
                    row = bench_steps(name, "full", n, args.steps)
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    print(f"{row['env']:<20} {row['mode']:<12} {row['num_envs']:>8} {row['per_s']:>12} "
                          f"{row['us_each']:>10} {row['compile_s']:>9}", flush=True)


if __name__ == "__main__":
    main()
