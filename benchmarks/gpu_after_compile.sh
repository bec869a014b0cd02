#!/usr/bin/env bash
# Issue 9: training throughput at the library's defaults for the batched cases, and the CLI end to end on the GPU
# twice with a persistent compilation cache (cold, then warm).
# Usage: benchmarks/gpu_after_compile.sh OUTDIR [CASES] [NAME]
#   session 5 (rollout not unrolled, init with the threefry kernel): the defaults -> train-after-compile.json
#   session 6: CASES="rocksample_11_11:gru:10 battleship_10:gru:5" NAME=train-after-session6
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"rocksample_11_11:gru:10 battleship_10:gru:5 tmaze_10:gru:1 tmaze_10:memoryless:30"}
NAME=${3:-train-after-compile}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
timeout 330 python3 benchmarks/bench_train.py --cases $CASES --updates 60 --json $OUT_DIR/$NAME.json 2>&1 | grep -v -E "$F"
for i in 1 2; do
  POBAX_COMPILE_CACHE=$OUT_DIR/xla timeout 100 python3 cli.py train --env tmaze_10 --memory gru --num-seeds 4 \
    --total-steps 102400 --out $OUT_DIR/cli-run-$i 2>&1 | grep -v -E "$F" | tail -n 3
  python3 -c "import json; s=json.load(open('$OUT_DIR/cli-run-$i/summary.json')); print('compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
done
rm -rf $OUT_DIR/xla
