"""The whole benchmark suite in one command: env-only and training throughput, next to the original's figures.

    python benchmarks/run_all.py --quick                                  # CPU smoke run, a couple of minutes
    python benchmarks/run_all.py --md results.md --json results.json       # the full suite
    python benchmarks/run_all.py --compile-cache /tmp/jax-cache            # + compile time with a warm cache

Env-only (`bench_env.bench`): random legal actions, auto-reset, vmapped over 1 / 64 / 1024 envs on CPU and
1 / 1024 / 8192 on GPU (`--num-envs`), for the environments of `--envs`; an environment whose pip extra is not
installed is skipped with a note. Training (`bench_train.case_config` + `pobax.eval.train`): the cases of
`--train-cases` (ENV:MEMORY:SEEDS, MEMORY one of memoryless, gru, trxl, ld) at the paper's settings for the
environment (as `bench_train.py`): one run, a vmapped batch of `--seeds` seeds, and seeds × the
paper's hyperparameter grid (`tmaze_10:gru:5xgrid`: 5 seeds of each of `PAPER_GRID`'s 24 sets, 120 runs in one
program, as `pobax sweep` trains them). Each row has
steps/s, compile seconds and the peak device memory so far (`memory_stats()`, "n/a" where the backend has
none, e.g. CPU), and — where known — the original implementation's figure on the same kind of device and our
ratio to it (>1: faster). With `--compile-cache DIR` the persistent compilation cache is on, and the first
training case is run a second time after dropping the in-memory caches: its compile seconds then show what
a warm persistent cache saves. `--deterministic` trains with `TrainConfig.deterministic`. Writes a Markdown table
(`--md`) and a JSON file (`--json`).
"""

import argparse
import datetime
import json
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench_env, bench_train

import jax  # noqa: E402

DEFAULT_ENVS = ["tmaze_10", "rocksample_11_11", "battleship_10", "Navix-DMLab-Maze-01-v0", "Walker-V-v0",
                "HalfCheetah-V-v0"]
QUICK_ENVS = ["tmaze_10", "rocksample_11_11", "battleship_10"]

# The original implementation's figures (issue 9), by device class. Env-only: steps/s at a number of envs.
# Training: (steps/s, compile s or None) per ENV:MEMORY:SEEDS at the same paper settings.
ORIGINAL_ENV = {
    "h200": {
        ("tmaze_10", 8192): 409e6, ("rocksample_11_11", 8192): 126e6, ("battleship_10", 8192): 49e6,
    },
    "cpu": {  # 2-core CPU
        ("tmaze_10", 1): 278e3, ("tmaze_10", 64): 1.68e6, ("tmaze_10", 1024): 2.54e6,
        ("rocksample_11_11", 1): 56e3, ("rocksample_11_11", 64): 633e3, ("rocksample_11_11", 1024): 1.47e6,
        ("battleship_10", 1): 59e3, ("battleship_10", 64): 63e3, ("battleship_10", 1024): 92e3,
        ("Walker-V-v0", 1): 5.3e3, ("Walker-V-v0", 64): 7.7e3, ("Walker-V-v0", 1024): 10.3e3,
        ("HalfCheetah-V-v0", 1): 1.1e3, ("HalfCheetah-V-v0", 64): 2.3e3, ("HalfCheetah-V-v0", 1024): 2.4e3,
        ("Navix-DMLab-Maze-01-v0", 1): 10.8e3, ("Navix-DMLab-Maze-01-v0", 64): 29e3,
        ("Navix-DMLab-Maze-01-v0", 1024): 30e3,
    },
}
ORIGINAL_TRAIN = {
    "h200": {
        "tmaze_10:gru:1": (7.9e3, 13.0), "tmaze_10:gru:30": (247e3, 13.5), "tmaze_10:memoryless:30": (2.15e6, None),
        "rocksample_11_11:gru:1": (9.2e3, 19.0), "battleship_10:gru:1": (30.7e3, 27.0),
    },
    "cpu": {
        "tmaze_10:gru:1": (20.5e3, 10.5), "tmaze_10:memoryless:1": (90e3, None),  # seed count not stated
        "rocksample_11_11:gru:1": (428.0, None), "battleship_10:gru:1": (117.5, None),  # reported as 100–135
        "tmaze_10:trxl:1": (1.4e3, None),  # "~1,400"
    },
}


def device_class() -> str:
    """Which reference figures apply: "h200" on GPUs (exact only on an H200), "cpu" on CPUs (a 2-core one)."""
    return "cpu" if jax.default_backend() == "cpu" else "h200"


def peak_memory() -> str:
    stats = jax.devices()[0].memory_stats()
    if not stats or "peak_bytes_in_use" not in stats:
        return "n/a"
    return f"{stats['peak_bytes_in_use'] / 2**20:,.0f} MiB"


def fmt(x: float | None) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return ""
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= scale:
            return f"{x / scale:.3g}{unit}"
    return f"{x:.3g}"


def ratio(ours: float, ref: float | None) -> str:
    return f"{ours / ref:.2f}×" if ref else ""


def env_rows(envs, num_envs, steps) -> tuple[list[dict], list[str]]:
    from bench_env import bench

    rows, notes = [], []
    refs = ORIGINAL_ENV[device_class()]
    for name in envs:
        for n in num_envs:
            try:
                r = bench(name, n, steps)
            except ImportError as e:  # the environment's pip extra is not installed
                import pobax.env as E

                extra = E.spec(name).family.extra
                notes.append(f"{name}: skipped, `pip install pobax[{extra}]` missing ({e.__class__.__name__}: {e})")
                print(f"skip {name}: {e}", flush=True)
                break
            r["peak_memory"] = peak_memory()
            r["original_steps_per_s"] = refs.get((name, n))
            rows.append(r)
            print(f"env   {name:28s} {n:6d} envs {r['steps_per_s']:>14,.0f} steps/s  compile {r['compile_s']:6.1f} s"
                  f"  original {fmt(r['original_steps_per_s']) or '-'}", flush=True)
    return rows, notes


def train_row(case: str, updates: int, label: str | None = None, deterministic: bool = False) -> dict:
    from bench_train import case_config, parse_case

    from pobax.agent import run_layout
    from pobax.eval import train

    env, memory, seeds, grid, obs = parse_case(case)
    cfg = case_config(env, memory, seeds, updates, None, *obs, grid=grid, deterministic=deterministic)
    runs = len(run_layout(cfg)[0])
    r = train(cfg, save=False, progress=False)
    ref = ORIGINAL_TRAIN[device_class()].get(case)
    row = dict(case=label or case, env=env, memory=memory, seeds=seeds, runs=runs, steps_per_s=r.steps_per_s,
               steps_per_s_per_run=r.steps_per_s / runs, compile_s=r.compile_s, peak_memory=peak_memory(),
               num_envs=cfg.num_envs, hidden_size=cfg.hidden_size, updates=updates,
               original_steps_per_s=ref[0] if ref else None, original_compile_s=ref[1] if ref else None)
    print(f"train {row['case']:40s} {r.steps_per_s:>12,.0f} steps/s  compile {r.compile_s:6.1f} s"
          f"  original {fmt(row['original_steps_per_s']) or '-'}", flush=True)
    return row


def markdown(meta: dict, env: list[dict], train: list[dict], notes: list[str]) -> str:
    ref_dev = "H200" if meta["reference_device"] == "h200" else "2-core CPU"
    out = [f"# pobax benchmarks: {meta['device']}, jax {meta['jax']}, {meta['date']}", "",
           f"Command: `{meta['command']}`", "",
           f"Original figures are the original implementation's on the {ref_dev} (issue 9); ratio = ours / original.",
           ""]
    if env:
        out += ["## Env-only", "", "| env | envs | steps/s | compile s | peak memory | original | ratio |",
                "|---|---|---|---|---|---|---|"]
        for r in env:
            out.append(f"| {r['env']} | {r['num_envs']} | {r['steps_per_s']:,.0f} | {r['compile_s']:.1f} | "
                       f"{r['peak_memory']} | {fmt(r['original_steps_per_s'])} | "
                       f"{ratio(r['steps_per_s'], r['original_steps_per_s'])} |")
        out.append("")
    if train:
        out += ["## Training", "",
                "| case | runs | env steps/s | per run | compile s | peak memory | original | ratio | original compile s |",
                "|---|---|---|---|---|---|---|---|---|"]
        for r in train:
            oc = r["original_compile_s"]
            out.append(f"| {r['case']} | {r['runs']} | {r['steps_per_s']:,.0f} | {r['steps_per_s_per_run']:,.0f} | "
                       f"{r['compile_s']:.1f} | {r['peak_memory']} | {fmt(r['original_steps_per_s'])} | "
                       f"{ratio(r['steps_per_s'], r['original_steps_per_s'])} | {'' if oc is None else oc} |")
        out.append("")
    if notes:
        out += ["Notes:", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(out)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cpu = jax.default_backend() == "cpu"
    p.add_argument("--quick", action="store_true",
                   help="small CPU-friendly run: 3 envs at 1/64 envs × 100 steps, T-Maze training at 8 updates")
    p.add_argument("--envs", nargs="*", default=None, help=f"env-only environments (default: {DEFAULT_ENVS})")
    p.add_argument("--num-envs", nargs="+", type=int, default=None,
                   help="env-only batch sizes (default: 1 64 1024 on CPU, 1 1024 8192 on GPU)")
    p.add_argument("--steps", type=int, default=None, help="env-only steps per env (default 200 on CPU, 1000 on GPU)")
    p.add_argument("--seeds", type=int, default=None, help="seeds of the vmapped batch (default 30; quick 4)")
    p.add_argument("--train-cases", nargs="*", default=None,
                   help="ENV:MEMORY:SEEDS, SEEDS a number or Nxgrid for N seeds × the paper's 24-set grid (default: "
                        "T-Maze GRU at 1 and --seeds seeds, memoryless at --seeds, GRU at 5xgrid (quick: 2xgrid), "
                        "TrXL at 1; RockSample 11 and Battleship 10 GRU at 1 and --seeds)")
    p.add_argument("--updates", type=int, default=None, help="PPO updates per training case (default 12 on CPU, "
                                                              "40 on GPU; quick 8)")
    p.add_argument("--compile-cache", default=None, metavar="DIR",
                   help="turn on JAX's persistent compilation cache in DIR and re-run the first training case")
    p.add_argument("--deterministic", action="store_true", help="train with TrainConfig.deterministic")
    p.add_argument("--md", default="run_all.md", help="Markdown output path")
    p.add_argument("--json", default="run_all.json", help="JSON output path")
    args = p.parse_args()

    seeds = args.seeds or (4 if args.quick else 30)
    envs = args.envs if args.envs is not None else (QUICK_ENVS if args.quick else DEFAULT_ENVS)
    num_envs = args.num_envs or ([1, 64] if args.quick else [1, 64, 1024] if cpu else [1, 1024, 8192])
    steps = args.steps or (100 if args.quick else 200 if cpu else 1000)
    updates = args.updates or (8 if args.quick else 12 if cpu else 40)
    if args.train_cases is not None:
        cases = args.train_cases
    elif args.quick:
        cases = ["tmaze_10:gru:1", f"tmaze_10:gru:{seeds}", f"tmaze_10:memoryless:{seeds}", "tmaze_10:gru:2xgrid"]
    else:
        cases = ["tmaze_10:gru:1", f"tmaze_10:gru:{seeds}", f"tmaze_10:memoryless:{seeds}", "tmaze_10:gru:5xgrid",
                 "tmaze_10:trxl:1", "rocksample_11_11:gru:1", f"rocksample_11_11:gru:{seeds}", "battleship_10:gru:1",
                 f"battleship_10:gru:{seeds}"]

    notes = []
    if args.compile_cache:
        fresh = not os.path.isdir(args.compile_cache) or not os.listdir(args.compile_cache)
        jax.config.update("jax_compilation_cache_dir", args.compile_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
        notes.append(f"persistent compilation cache in {args.compile_cache} ({'empty' if fresh else 'not empty'} "
                     "at start: first-run compile times are " + ("cold)" if fresh else "possibly warm)"))
    meta = dict(device=f"{jax.devices()[0].device_kind} ({jax.default_backend()})", jax=jax.__version__,
                date=datetime.date.today().isoformat(), command=" ".join(["python"] + sys.argv),
                reference_device=device_class(), env_steps=steps, updates=updates, deterministic=args.deterministic)
    if not cpu and "h200" not in jax.devices()[0].device_kind.lower():
        notes.append(f"the original's GPU figures are on an H200, this device is {jax.devices()[0].device_kind}")
    print(f"device: {meta['device']}, jax {meta['jax']}", flush=True)

    t0 = time.perf_counter()
    env, env_notes = env_rows(envs, num_envs, steps)
    notes += env_notes
    train = [train_row(c, updates, deterministic=args.deterministic) for c in cases]
    if args.compile_cache and cases:
        jax.clear_caches()  # as in a new process: only the persistent cache can serve the compiled programs
        train.append(train_row(cases[0], updates, label=f"{cases[0]} (2nd run, persistent cache)",
                               deterministic=args.deterministic))
    meta["wall_s"] = time.perf_counter() - t0

    md = markdown(meta, env, train, notes)
    print("\n" + md, flush=True)
    if args.md:
        with open(args.md, "w") as f:
            f.write(md)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(meta=meta, env=env, train=train, notes=notes), f, indent=2)


if __name__ == "__main__":
    main()
