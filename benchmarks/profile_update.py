"""Where the time of one PPO update goes: rollout, GAE, replay (minibatch epochs, forward + backward).

    python benchmarks/profile_update.py --cases tmaze_10:gru:30 tmaze_10:gru:1 --iters 20
    python benchmarks/profile_update.py --cases ant_pixels:gru:3 ant_pixels:trxl:3 --num-envs 16 --iters 2

A case is ENV:MEMORY:SEEDS[:OBSERVABILITY] at the paper's settings (as `bench_train.py`, `Nxgrid` included;
`--num-envs` replaces its environments per run). Three programs are compiled, each running `--iters` updates' worth
of work in one `lax.scan`, vmapped over the runs, with the layers' choice of product as in training
(`with_matmul_batch`): (a) rollouts only, (b) rollouts + GAE, (c) whole updates (`--gae-method`: `pobax.agent.gae`'s
`method` in (b) and (c), default "auto" as in training). GAE = (b) − (a), replay = (c) −
(b). For the whole update, the network's floating-point operations are counted from its weight matrices (2 FLOPs per
weight per sample; a forward in the rollout and forward + backward ≈ 3 forwards per epoch in the replay;
environment and optimiser work excluded, as are convolutions): with `--peak-tflops` (e.g. H200: 67 TFLOP/s fp32) it
prints the fraction of the device's arithmetic reached. (XLA's own cost analysis counts a loop body once, not per
iteration, so it is not used.) It also counts the sequential time steps an update executes (rollout + GAE + epochs
× minibatches × forward and backward) and the time per sequential step, which bounds a latency-bound workload.

Bytes and kernels: `pobax._hlo.traffic` walks each compiled program's optimised HLO, loops multiplied by their
trip counts, and sums the bytes every kernel reads and writes (caches ignored: an upper bound on memory
traffic) and the kernels launched; per update, and with `--peak-gbs` (e.g. H200: 4800 GB/s) the fraction of the
device's memory bandwidth that traffic would use at the measured time. `--backend NAME=VALUE` replaces choices of
`pobax/_backend.py` (`TrainConfig.backend`), e.g. `gru_impl=dot` or `rollout_reduce_limit=0`.
"""

import argparse
import dataclasses
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench_env, bench_train

import equinox as eqx  # noqa: E402
import jax  # noqa: E402

from bench_train import case_config, parse_case  # noqa: E402
from pobax._cli.args import ScriptParser
from pobax._backend import parse_overrides  # noqa: E402
from pobax._hlo import traffic  # noqa: E402
from pobax.agent import Runs, gae, rollout, structural, update  # noqa: E402
from pobax.agent._ppo import rollout_rows  # noqa: E402
from pobax.agent._train import run_hyperparams  # noqa: E402


def programs(cfg, env, batch, iters: int, gae_method: str = "auto"):
    """The three programs, each `iters` updates' worth in one scan; `batch`: the layers' `(rows, limit)` as training
    passes them (`update`'s `matmul_batch`)."""
    def rollouts(state, hp):
        return jax.lax.scan(lambda s, _: (rollout(cfg, env, s, batch)[0], None), state, None, length=iters)[0]

    def rollouts_gae(state, hp):
        def body(s, _):
            s, traj = rollout(cfg, env, s, batch)
            adv, _ = gae(traj["reward"], traj["values"][..., 0], traj["next_values"][..., 0], traj["terminated"],
                         traj["truncated"], env.gamma, hp.lambda0, method=gae_method)
            # the advantages feed the carry so that XLA cannot drop the GAE
            return eqx.tree_at(lambda t: t.episode.ret, s, s.episode.ret + 0.0 * adv.sum()), None
        return jax.lax.scan(body, state, None, length=iters)[0]

    def updates(state, hp):
        return jax.lax.scan(lambda s, _: (update(cfg, env, s, hp, batch, gae_method)[0], None), state, None, length=iters)[0]

    return {name: eqx.filter_jit(jax.vmap(f)) for name, f in
            (("rollout", rollouts), ("rollout+gae", rollouts_gae), ("update", updates))}


def timed(fn, state, hp, iters: int, repeats: int = 3):
    t0 = time.perf_counter()
    compiled = fn.lower(state, hp).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(state, hp))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(state, hp))
        best = min(best, time.perf_counter() - t0)
    return best / iters, compile_s, traffic(compiled.compiled.as_text())  # equinox wraps jax.stages.Compiled


def main():
    p = ScriptParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["tmaze_10:gru:1", "tmaze_10:gru:30"])
    p.add_argument("--iters", type=int, default=20, help="updates per timed program")
    p.add_argument("--peak-tflops", type=float, default=None, help="device peak fp32 TFLOP/s, for the fraction")
    p.add_argument("--peak-gbs", type=float, default=None, help="device memory bandwidth GB/s, for the fraction")
    p.add_argument("--gae-method", default="auto", choices=["auto", "weights", "associative", "sequential"],
                   help="GAE computation of the rollout+GAE program (pobax.agent.gae's method)")
    p.add_argument("--backend", nargs="+", default=[], metavar="NAME=VALUE",
                   help="replace choices of pobax/_backend.py (TrainConfig.backend), e.g. gru_impl=dot")
    p.add_argument("--num-envs", type=int, default=None,
                   help="environments per run instead of the paper's (e.g. 16, the pixel suite's `reduced` budget)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    overrides = ",".join(args.backend)
    try:
        parse_overrides(overrides)
    except ValueError as e:
        raise SystemExit(f"--backend: {e}") from None
    device = f"{jax.devices()[0].device_kind} ({jax.devices()[0].platform})"
    print(f"device: {device}, jax {jax.__version__}")
    rows = []
    for case in args.cases:
        env_id, memory, seeds, grid, obs = parse_case(case)
        sizes = {} if args.num_envs is None else dict(num_envs=args.num_envs)
        cfg = dataclasses.replace(case_config(env_id, memory, seeds, 10, None, *obs, grid=grid, **sizes), seed=0,
                                  backend=overrides)
        run_set = Runs(cfg, devices=jax.local_devices()[:1])
        env, runs = run_set.env, run_set.num_runs
        scfg = structural(cfg, run_set.backend)
        batch = (rollout_rows(runs, cfg.num_envs), run_set.backend.reduce_limit())
        state = run_set.init()
        hp = run_hyperparams(cfg)
        t, traf = {}, {}
        for name, fn in programs(scfg, env, batch, args.iters, args.gae_method).items():
            t[name], compile_s, traf[name] = timed(fn, state, hp, args.iters)
            t[name + " compile"] = compile_s
        per_update = t["update"]
        rollout_s, gae_s = t["rollout"], max(t["rollout+gae"] - t["rollout"], 0.0)
        replay_s = max(per_update - t["rollout+gae"], 0.0)
        seq = cfg.num_steps * (2 + 2 * cfg.update_epochs * cfg.num_minibatches)
        steps = runs * cfg.num_envs * cfg.num_steps
        model = jax.tree.map(lambda x: x[0], state.model)
        macs = sum(x.size for x in jax.tree.leaves(eqx.filter(model, eqx.is_array)) if x.ndim == 2)
        flops = steps * 2 * macs * (1 + 3 * cfg.update_epochs)
        row = dict(case=case, num_envs=cfg.num_envs, device=device, jax=jax.__version__, gae_method=args.gae_method,
                   backend=parse_overrides(overrides), update_ms=per_update * 1e3,
                   rollout_ms=rollout_s * 1e3, gae_ms=gae_s * 1e3, replay_ms=replay_s * 1e3,
                   env_steps_per_s=steps / per_update, flops_per_update=flops, tflops=flops / per_update / 1e12,
                   sequential_steps=seq, us_per_sequential_step=per_update / seq * 1e6,
                   compile_update_s=t["update compile"],
                   bytes_per_update={k: v["bytes"] / args.iters for k, v in traf.items()},
                   kernels_per_update={k: v["kernels"] / args.iters for k, v in traf.items()},
                   uncounted_loops=traf["update"]["uncounted_loops"])
        row["gbs"] = row["bytes_per_update"]["update"] / per_update / 1e9
        rows.append(row)
        print(f"\n{case}: {per_update * 1e3:.2f} ms per update ({row['env_steps_per_s']:,.0f} env steps/s), "
              f"compile {t['update compile']:.1f} s")
        for name, v in (("rollout", rollout_s), ("GAE", gae_s), ("replay (epochs × minibatches, fwd+bwd)", replay_s)):
            print(f"  {name:42s} {v * 1e3:8.2f} ms  {100 * v / per_update:5.1f}%")
        frac = ""
        if args.peak_tflops:
            frac += f" = {100 * row['tflops'] / args.peak_tflops:.3f}% of {args.peak_tflops} TFLOP/s"
        print(f"  network arithmetic: {flops / 1e9:.3f} GFLOP per update -> {row['tflops']:.4f} TFLOP/s{frac}")
        print(f"  {seq} sequential time steps per update -> {row['us_per_sequential_step']:.2f} µs each")
        b, k = row["bytes_per_update"], row["kernels_per_update"]
        frac = f" = {100 * row['gbs'] / args.peak_gbs:.2f}% of {args.peak_gbs:g} GB/s" if args.peak_gbs else ""
        print(f"  memory traffic (kernels' operands and results, no cache): {b['update'] / 1e6:.1f} MB per update "
              f"(rollout {b['rollout'] / 1e6:.1f}, rollout+GAE {b['rollout+gae'] / 1e6:.1f}) -> {row['gbs']:.1f} GB/s{frac}")
        print(f"  kernels per update: {k['update']:,.0f} (rollout {k['rollout']:,.0f}, rollout+GAE {k['rollout+gae']:,.0f})"
              f" -> {per_update / k['update'] * 1e6:.2f} µs per kernel"
              + (f"; {row['uncounted_loops']} loops without a known trip count, counted once" if row["uncounted_loops"] else ""))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
