#!/usr/bin/env bash
# Issue 9, compile time, session 7: the library (autotuner without the block-level emitter and cuBLASLt fission,
# `_train.GPU_COMPILER_OPTIONS`) against the previous commit (d57be96, extracted to .gapprev/ as
# gpu_compile_session6.sh says), alternating, fresh processes, persistent cache off; then a short CLI run of a CNN
# (pixels) and a Transformer-XL agent with the options on. Usage: benchmarks/gpu_compile_session7.sh OUTDIR "CASES" [ROUNDS]
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"rocksample_11_11:gru:1 tmaze_10:gru:30 battleship_10:gru:1 tmaze_10:gru:1"}
"$(dirname "$0")/gpu_compile_session6.sh" "$OUT_DIR" "$CASES" "${3:-2}"
F="warp|UserWarning|warnings.warn|^$|settotalmass|Delay kernel"
for run in "ant_pixels gru" "tmaze_10 trxl"; do
  set -- $run
  timeout 150 python3 cli.py train --env $1 --memory $2 --num-seeds 2 --total-steps 16384 --num-chunks 2 \
    --out $OUT_DIR/cli-$1-$2 2>&1 | grep -v -E "$F" | tail -n 2
  python3 -c "import json; s=json.load(open('$OUT_DIR/cli-$1-$2/summary.json')); print('$1 $2 compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
  rm -rf $OUT_DIR/cli-$1-$2
done
