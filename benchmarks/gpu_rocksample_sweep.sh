#!/usr/bin/env bash
# Issue 3: why GRU agents on RockSample(11, 11) collapse to "walk east and exit" (entropy → 0 by ~1M steps in
# gpu_rocksample_gap.sh, while the memoryless floor keeps entropy ~2.3 and samples rocks). Four programs side by
# side: GRU on partial and on perfect_memory, each with and without the previous action, every one a grid of
# lr {2.5e-3, 2.5e-4, 2.5e-5} × λ0 {0.5, 0.95} × 3 seeds at 2M steps (paper settings otherwise).
# Usage: benchmarks/gpu_rocksample_sweep.sh OUTDIR [STEPS] [LIMIT]
set -u
OUT_DIR=${1:?output directory}; STEPS=${2:-2000000}; LIMIT=${3:-480}
W=/tmp/rssweep; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.22
T="python3 cli.py train --env rocksample_11_11 --memory gru --preset paper --total-steps $STEPS --num-seeds 3 --lr 2.5e-3 2.5e-4 2.5e-5 --lambda0 0.5 0.95 --num-chunks 10 --quiet"
for obs in partial perfect_memory; do for ac in action-concat no-action-concat; do
  timeout $LIMIT $T --observability $obs --$ac --out $W/$obs-$ac > $W/$obs-$ac.log 2>&1 &
done; done
wait
cd $W && tar czf "$OUT_DIR/rssweep.tgz" *.log */summary.json */config.json */metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "^$" "$f" | tail -n 4; done
for d in $W/*/; do python3 - "$d" <<'PY'
import json, sys
d = sys.argv[1]
try:
    s = json.load(open(d + "summary.json"))
except FileNotFoundError:
    print(d, "unfinished"); sys.exit()
for x in s["sets"]:
    print(d.split("/")[-2], f"lr={x['lr']:g} l0={x['lambda0']}", "disc", round(x["disc_return"]["mean"], 2),
          [round(v, 2) for v in x["disc_return"]["per_seed"]], "| steps/s", round(s["steps_per_s"]))
PY
done
