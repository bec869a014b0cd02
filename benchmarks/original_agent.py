"""The original implementation's PPO (PyPI `pobax==0.0.1`) trained as a black box, one seed per process, its learning
curves summarised: the agent-side counterpart of `benchmarks/parity.py`.

    python benchmarks/original_agent.py --original-python /tmp/origvenv/bin/python --seeds 40000 40001 40002 \\
        --json benchmarks/results/rocksample11-original-agent-cpu.json -- \\
        --env rocksample_11_11 --num_envs 8 --action_concat --hidden_size 256 --entropy_coeff 0.2 \\
        --lr 0.0025 --lambda0 0.3 --total_steps 500000

Everything after `--` goes to the original's `python -m pobax.algos.ppo` command line as is (its own flags, with
underscores; `--n_seeds 1 --seed S` are added per seed). `--algo transformer_xl` runs its Transformer-XL module
instead (`python -m pobax.algos.transformer_xl`, the same flags plus `--embed_size`, `--num_layers`...), which calls
the env factory without its `num_envs` (filled here from `--num_envs`) and then fails on every environment tried
(docs/parity.md, "Its Transformer-XL does not start"). Each seed runs in a process of its own under
`--original-python`, an interpreter of a separate virtual environment where `pobax==0.0.1` is installed (the two
packages share the import name `pobax`, so never in one process): on a 2-core CPU the original's `--n_seeds 5` program
stalls (every thread waiting, no CPU time used after its first seconds), while one seed per process finishes.

The original is used through its command line and what it saves (an orbax checkpoint whose `out/metric` holds, per
update, step and environment, `returned_episode`, `returned_episode_returns`, `returned_discounted_episode_returns`,
`returned_episode_lengths`); its source is not read. Its import takes the shims of `benchmarks/parity.py`
(`ORIGINAL_SHIMS`, through its `_original_imports`).
`--peel NAME ...` leaves the named outermost wrappers off what its environment factory (`pobax.envs.get_env`) returns,
by their `_env` attribute: its RockSample factory wraps the environment in `NormalizeVecReward`, peeled by default
(raw rewards); `--peel` with no names trains RockSample as the factory builds it, its rewards normalised (the
normaliser fails at reset in the released package without the `Observation.shape` shim of `ORIGINAL_SHIMS`).
`--reward-scale X` multiplies the reward the original's agent trains on by X (its logged returns stay raw): a behaviour
that changes with the scale of the rewards tells, from outside, whether its policy gradient is scale-free (advantages
standardised) or not.

Per seed the JSON keeps the shapes of the saved network's parameters (`param_shapes`, by their names in the
checkpoint) and their spread (`param_stats`: std, mean and root mean square of each; with `--lr 1e-9` and
`--total_steps` of one update, the initialisation's), the discounted return and episode length of the episodes
completed in each of `--bins` equal spans of the updates, and the final returns (discounted and undiscounted) as
`pobax` defines them (`pobax.eval._stats.final_value`: the mean return of each update with a finished episode,
then the mean of the last 10% of those updates).
"""

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time

from parity import ORIGINAL_SHIMS, PEELED, REPO

#: The original's training modules (`python -m pobax.algos.NAME`): its PPO and its Transformer-XL PPO.
ALGOS = ("ppo", "transformer_xl")


class _ScaleReward:
    """The original's (vectorised) environment with its step's reward, the third value it returns, multiplied by
    `scale`; everything else passes through. Its episode statistics are logged further in, so stay in raw units."""

    def __init__(self, env, scale: float):
        self._env, self._scale = env, scale

    def __getattr__(self, name):
        return getattr(self._env, name)

    def step(self, *args, **kwargs):
        out = self._env.step(*args, **kwargs)
        return (*out[:2], out[2] * self._scale, *out[3:])


def worker(args: argparse.Namespace, ppo_args: list[str]) -> None:
    """In the original's interpreter: the shims, the peeled factory, its PPO's `__main__`, then its saved curves."""
    import builtins  # noqa: PLC0415
    import runpy  # noqa: PLC0415

    from parity import _original_imports  # noqa: PLC0415  (the shims; this file's directory is on sys.path)

    _original_imports()
    import jax  # noqa: PLC0415
    import pobax.envs as envs  # noqa: PLC0415  (the original's package)

    factory, peeled = envs.get_env, []
    num_envs = int(ppo_args[ppo_args.index("--num_envs") + 1]) if "--num_envs" in ppo_args else 4  # its default

    def get_env(*a, **k):
        if len(a) < 3 and "num_envs" not in k:  # its transformer_xl calls the factory without it (a TypeError)
            k["num_envs"] = num_envs
        out = factory(*a, **k)
        env = out[0]
        while type(env).__name__ in args.peel:
            peeled.append(type(env).__name__)
            env = env._env
        if args.reward_scale != 1.0:
            env = _ScaleReward(env, args.reward_scale)
        return (env, *out[1:])

    envs.get_env = get_env
    saved = []
    real_print = print

    def spy(*a, **k):  # the original prints where it saved its results
        text = " ".join(str(x) for x in a)
        if text.startswith("Saving results to "):
            saved.append(text[len("Saving results to "):].strip())
        real_print(*a, **k)

    builtins.print = spy
    sys.argv = ["ppo", *ppo_args]
    t0 = time.time()
    try:
        runpy.run_module(f"pobax.algos.{args.algo}", run_name="__main__", alter_sys=True)
    finally:
        builtins.print = real_print
    wall = time.time() - t0
    if not saved:
        raise SystemExit("the original's PPO did not say where it saved its results")
    import numpy as np  # noqa: PLC0415
    import orbax.checkpoint as ocp  # noqa: PLC0415

    restored = ocp.PyTreeCheckpointer().restore(saved[-1])
    metric = restored["out"]["metric"]
    shape = np.asarray(metric["returned_episode"]).shape  # (sweep axes of size 1..., updates, steps, envs)
    get = lambda k: np.asarray(metric[k]).reshape(-1, *shape[-3:])[0]  # noqa: E731  (the one seed's)
    done, disc, undisc, length = (get("returned_episode"), get("returned_discounted_episode_returns"),
                                  get("returned_episode_returns"), get("returned_episode_lengths"))
    params, stats = {}, {}

    def walk(tree, path):  # the saved network's parameter shapes (the sweep axes dropped) and the one seed's spread
        if isinstance(tree, dict):
            for k, v in tree.items():
                walk(v, f"{path}/{k}" if path else str(k))
        elif hasattr(tree, "shape"):
            params[path] = [int(s) for s in tree.shape][len(shape) - 3:]
            x = np.asarray(tree).reshape(-1, *params[path])[0].astype(np.float64)
            stats[path] = {"std": float(x.std()), "mean": float(x.mean()), "rms": float(np.sqrt((x * x).mean()))}

    walk(restored.get("final_train_state", {}).get("params", {}), "")
    updates = done.shape[0]
    spans = np.array_split(np.arange(updates), args.bins)
    mean = lambda x, u: float(x[u][done[u]].mean()) if done[u].any() else None  # noqa: E731

    out = {"saved_to": saved[-1], "wall_s": wall, "metric_shape": list(shape), "updates": updates,
           "samples_per_update": int(done.shape[1] * done.shape[2]), "peeled": peeled, "param_shapes": params,
           "param_stats": stats,
           "curve_disc": [mean(disc, u) for u in spans], "curve_length": [mean(length, u) for u in spans],
           "episodes": int(done.sum()),
           # per-update means (None where no episode ended): `main` takes pobax's final value of them
           "per_update_disc": [mean(disc, u) for u in range(updates)],
           "per_update_undisc": [mean(undisc, u) for u in range(updates)],
           "versions": {"jax": jax.__version__, "python": platform.python_version()}}
    with open(args.out, "w") as f:
        json.dump(out, f)


def main() -> None:
    argv = sys.argv[1:]
    ppo_args = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[40000], help="one process per seed, in this order")
    p.add_argument("--peel", nargs="*", default=list(PEELED),
                   help="outermost wrappers of the original's env factory to leave off (by class name)")
    p.add_argument("--bins", type=int, default=5, help="spans of updates in each seed's curve")
    p.add_argument("--algo", choices=ALGOS, default="ppo",
                   help="the original's training module: ppo (memoryless, GRU, λ-discrepancy) or transformer_xl")
    p.add_argument("--reward-scale", type=float, default=1.0,
                   help="multiply the reward the agent trains on (the logged returns stay raw)")
    p.add_argument("--original-python", default="/tmp/origvenv/bin/python")
    p.add_argument("--timeout", type=int, default=7200, help="seconds per seed")
    p.add_argument("--json", help="write the results here (rewritten after every seed)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args, ppo_args)
        return
    import numpy as np  # noqa: PLC0415  (here, not in the worker's interpreter: the original's)

    from pobax.eval._stats import final_value  # noqa: PLC0415

    if not ppo_args:
        p.error("give the original's PPO flags after `--` (e.g. -- --env tmaze_10 --total_steps 100000)")
    if any(a in ("--seed", "--n_seeds") for a in ppo_args):
        p.error("--seed and --n_seeds are set per process from --seeds; leave them out after `--`")
    record = {"command": "python benchmarks/original_agent.py " + " ".join(sys.argv[1:]),
              "original": "pobax==0.0.1 (PyPI), run as a black box through its command line",
              "original_python": args.original_python, "algo": f"pobax.algos.{args.algo}",
              "original_shims": ORIGINAL_SHIMS + (["get_env's num_envs from --num_envs where the module leaves it out"]
                                                  if args.algo == "transformer_xl" else []),
              "ppo_args": ppo_args,
              "peel": args.peel, "bins": args.bins,
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "jax_platforms": os.environ.get("JAX_PLATFORMS", "")},
              "seeds": {}}
    for seed in args.seeds:
        out = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"original-agent-{os.getpid()}-{seed}.json")
        cmd = [args.original_python, os.path.abspath(__file__), "--worker", "--algo", args.algo, "--out", out,
               "--bins", str(args.bins),
               "--reward-scale", str(args.reward_scale), "--peel", *args.peel, "--", *ppo_args, "--n_seeds", "1",
               "--seed", str(seed)]
        t0 = time.time()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, cwd=REPO)
        if proc.returncode != 0 or not os.path.exists(out):
            lines = proc.stderr.strip().splitlines() or ["no output"]
            error = [ln for ln in lines if re.match(r"[\w.]+(Error|Exception|Exit)\b", ln)]  # not JAX's notes after it
            sys.exit(f"seed {seed}: the original's {args.algo} failed (exit {proc.returncode}): {(error or lines)[-1]}")
        with open(out) as f:
            row = json.load(f)
        os.unlink(out)
        for kind in ("disc", "undisc"):  # in this interpreter, where pobax (ours) imports
            value = final_value([np.nan if m is None else m for m in row.pop(f"per_update_{kind}")])
            row[f"final_{kind}"] = None if np.isnan(value) else value
        row["process_s"] = time.time() - t0
        record["seeds"][str(seed)] = row
        finals = [r["final_disc"] for r in record["seeds"].values()]
        fmt = lambda v, d: "none (no episode ended)" if v is None else f"{v:.{d}f}"  # noqa: E731
        print(f"seed {seed}: final discounted {fmt(row['final_disc'], 3)}, undiscounted {fmt(row['final_undisc'], 2)}; "
              f"curve {['%.2f' % c if c is not None else None for c in row['curve_disc']]}; "
              f"{row['process_s']:.0f} s", flush=True)
        record["final_disc_per_seed"] = finals
        if args.json:
            os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
            with open(args.json, "w") as f:
                json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
