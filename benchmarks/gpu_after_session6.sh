#!/usr/bin/env bash
# Issue 9, session 6: the batched issue-9 cases at the new defaults (throughput and compile), then the CLI twice with
# a persistent compilation cache (cold, then warm). Usage: benchmarks/gpu_after_session6.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
timeout 330 python3 benchmarks/bench_train.py --cases rocksample_11_11:gru:10 battleship_10:gru:5 \
  --updates 60 --json $OUT_DIR/train-after-session6.json 2>&1 | grep -v -E "$F"
for i in 1 2; do
  POBAX_COMPILE_CACHE=$OUT_DIR/xla timeout 100 python3 cli.py train --env tmaze_10 --memory gru --num-seeds 4 \
    --total-steps 102400 --out $OUT_DIR/cli-run-$i 2>&1 | grep -v -E "$F" | tail -n 3
  python3 -c "import json; s=json.load(open('$OUT_DIR/cli-run-$i/summary.json')); print('compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
done
rm -rf $OUT_DIR/xla
