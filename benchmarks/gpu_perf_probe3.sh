#!/usr/bin/env bash
# Third GPU probe for issue 9 (alone on the GPU), after removing the per-update conditional and making the
# GRU's recurrent product a fused multiply-reduce on accelerators: training throughput at the library's
# defaults for the target cases, unroll 8 for T-Maze, Battleship's GRU with both products, the CNN
# convolutions native vs matmul, and a warm persistent compilation cache. Usage: gpu_perf_probe3.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
cd benchmarks
timeout 200 python3 bench_train.py --updates 100 --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 \
  rocksample_11_11:gru:10 battleship_10:gru:1 battleship_10:gru:5 --json "$OUT_DIR/train.json" 2>&1 | grep -v -E "$F"
timeout 60 python3 bench_train.py --updates 100 --unroll 8 --cases tmaze_10:gru:30 2>&1 | grep -v -E "$F"
timeout 60 python3 bench_train.py --updates 100 --gru dot --cases battleship_10:gru:1 2>&1 | grep -v -E "$F"
timeout 150 python3 bench_train.py --updates 8 --conv matmul native \
  --cases Navix-DMLab-Maze-01-v0:memoryless:3:full 2>&1 | grep -v -E "$F"
cd ..
rm -rf /tmp/cc; for i in 1 2; do
  POBAX_COMPILE_CACHE=/tmp/cc timeout 60 python3 cli.py train --env tmaze_10 --memory gru --action-concat \
    --preset paper --num-seeds 30 --total-steps 200000 --quiet --out /tmp/cc-run$i 2>&1 | grep -v -E "$F" | tail -n 2
  python3 -c "import json; s=json.load(open('/tmp/cc-run$i/summary.json')); print('cache run $i: compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
done
