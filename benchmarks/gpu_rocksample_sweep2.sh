#!/usr/bin/env bash
# Issue 3, second sweep: does the entropy coefficient (the paper's 0.2) or λ0 keep the GRU on RockSample(11, 11)'s
# partial observation from learning? Three programs side by side, each the same grid of
# lr {2.5e-3, 2.5e-4} × λ0 {0.3, 0.95} × entropy {0.2, 0.05, 0.01} × 3 seeds (paper settings otherwise):
# GRU on partial, memoryless on partial (the floor), GRU on perfect_memory (the paper's ceiling).
# Result (H200, 1.5M steps): results/rocksample-sweep2-h200.json.
# Usage: benchmarks/gpu_rocksample_sweep2.sh OUTDIR [STEPS] [LIMIT]
set -u
OUT_DIR=${1:?output directory}; STEPS=${2:-2000000}; LIMIT=${3:-500}
W=/tmp/rssweep2; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
T="python3 cli.py train --env rocksample_11_11 --preset paper --total-steps $STEPS --num-seeds 3 --lr 2.5e-3 2.5e-4
   --lambda0 0.3 0.95 --entropy-coeff 0.2 0.05 0.01 --num-chunks 10 --quiet"
timeout $LIMIT $T --memory gru --observability partial --out $W/gru-partial > $W/gru-partial.log 2>&1 &
timeout $LIMIT $T --memory memoryless --observability partial --out $W/mlp-partial > $W/mlp-partial.log 2>&1 &
timeout $LIMIT $T --memory gru --observability perfect_memory --out $W/gru-pm > $W/gru-pm.log 2>&1 &
wait
cd $W && tar czf "$OUT_DIR/rssweep2.tgz" *.log */summary.json */config.json */metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "^$" "$f" | tail -n 3; done
python3 - $W <<'PY'
import csv, glob, sys, collections
for d in sorted(glob.glob(sys.argv[1] + "/*/")):
    rows = [r for f in sorted(glob.glob(d + "metrics/*.csv")) for r in csv.DictReader(open(f))]
    if not rows:
        continue
    last = max(int(r["update"]) for r in rows)
    tail = [r for r in rows if int(r["update"]) >= 0.9 * last]
    g = collections.defaultdict(list)
    for r in tail:
        if r["disc_return"] not in ("", "nan"):  # empty where no episode ended in that update
            g[(r["lr"][:6], r["lambda0"][:4], r["entropy_coeff"][:4])].append((float(r["disc_return"]), float(r["entropy"])))
    print(d.split("/")[-2], "at env step", max(int(r["env_step"]) for r in rows))
    for k, v in sorted(g.items()):
        print("  lr=%s l0=%s ent=%s  disc %.2f  entropy %.2f" % (*k, sum(x for x, _ in v) / len(v), sum(y for _, y in v) / len(v)))
PY
