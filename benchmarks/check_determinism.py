"""Does the same seed train the same run? A case (`bench_train.py`'s ENV:MEMORY:SEEDS[:OBSERVABILITY] at the paper's
settings; default RockSample 11 GRU, 1 seed) trained for `--updates` updates in this process: once, then (unless
`--once`) again with the same compiled programs, and once more after `jax.clear_caches()` (compiled again).

Prints the largest difference between the first run's final weights and each other run's, and checksums of the
final weights and of the metrics table (SHA-256 of their bytes, and the weights' float64 sum). Run the script in
several processes, one after the other or at once, and compare the checksums: each process compiles afresh (this
script does not turn the persistent compilation cache on; leave $POBAX_COMPILE_CACHE unset or "off"). On a GPU XLA
picks GEMM kernels by timing candidates unless `--deterministic` (`TrainConfig.deterministic`: XLA's deterministic
ops, no autotuning by timing), so near ties can train another run in another process.

    python benchmarks/check_determinism.py --case battleship_10:gru:1 --deterministic
    for i in 1 2 3; do python benchmarks/check_determinism.py --case tmaze_10:gru:1 --once & done; wait
"""

import argparse
import hashlib
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench_train

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

from bench_train import case_config, device_name, parse_case  # noqa: E402
from pobax._cli.args import ScriptParser
from pobax.eval import train  # noqa: E402


def weights(result) -> np.ndarray:
    """Every array of the final models (all runs), flattened into one float array."""
    leaves = jax.tree.leaves(eqx.filter(result.state.model, eqx.is_array))
    return np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in leaves])


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def metrics_array(result) -> np.ndarray:
    """The metrics table's numeric columns, in a fixed column order, as float64 (NaN where a metric has no value)."""
    df = result.metrics
    cols = sorted(c for c in df.columns if np.issubdtype(df[c].dtype, np.number))
    return df[cols].to_numpy(np.float64)


def main():
    p = ScriptParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--case", default="rocksample_11_11:gru:1")
    p.add_argument("--updates", type=int, default=40)
    p.add_argument("--deterministic", action="store_true", help="TrainConfig.deterministic")
    p.add_argument("--once", action="store_true", help="train once (for comparing processes only)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the checksums to this JSON file")
    args = p.parse_args()
    env_id, memory, seeds, grid, obs = parse_case(args.case)
    cfg = case_config(env_id, memory, seeds, args.updates, None, *obs, grid=grid, deterministic=args.deterministic)

    first = train(cfg, save=False, progress=False)
    w, m = weights(first), metrics_array(first)
    out = dict(case=args.case, updates=args.updates, deterministic=args.deterministic, device=device_name(),
               jax=jax.__version__, weights_sha256=digest(w), metrics_sha256=digest(m),
               weights_sum=float(w.sum()))
    print(f"device: {out['device']}, jax {out['jax']}, case {args.case}, {args.updates} updates, "
          f"deterministic={args.deterministic}")
    if not args.once:
        same = train(cfg, save=False, progress=False)  # the same executables
        jax.clear_caches()
        again = train(cfg, save=False, progress=False)  # compiled again
        for name, r in (("same executable", same), ("recompiled", again)):
            dw = float(np.abs(weights(r) - w).max())
            same_metrics = np.array_equal(metrics_array(r), m, equal_nan=True)
            out[name.replace(" ", "_")] = dict(max_weight_diff=dw, metrics_equal=bool(same_metrics))
            print(f"{name}: max|Δ weights| {dw!r}, metrics identical: {same_metrics}")
    print(f"checksums: weights {out['weights_sha256']} (sum {out['weights_sum']!r}), metrics {out['metrics_sha256']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
