#!/usr/bin/env bash
# Issue 9, compile time, session 7: the library (autotuner without the block-level emitter and cuBLASLt fission,
# `_train.GPU_COMPILER_OPTIONS`) against the previous commit (d57be96, extracted to .gapprev/ with
# `git archive d57be96 pobax benchmarks/bench_compile.py benchmarks/bench_train.py | tar -x -C .gapprev`), alternating,
# fresh processes, persistent cache off; then a short CLI run of a CNN (pixels) and a Transformer-XL agent with the
# options on. Usage: benchmarks/gpu_compile_session7.sh OUTDIR "CASES" [ROUNDS]
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"rocksample_11_11:gru:1 tmaze_10:gru:30 battleship_10:gru:1 tmaze_10:gru:1"}
ROUNDS=${3:-2}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$|^device|^case|settotalmass|Delay kernel"
BASE=$PYTHONPATH
OLDPATH=${BASE/$PWD/$PWD\/.gapprev}
for i in $(seq $ROUNDS); do
  for c in $CASES; do
    n=$(echo $c | tr ':' '_')
    PYTHONPATH=$BASE timeout 120 python3 benchmarks/bench_compile.py --updates 40 --cases $c --json $OUT_DIR/new-$n-$i.json 2>&1 | grep -v -E "$F" | sed 's/^/new /'
    (cd .gapprev && PYTHONPATH=$OLDPATH timeout 120 python3 benchmarks/bench_compile.py --updates 40 --cases $c \
      --json $OUT_DIR/old-$n-$i.json 2>&1 | grep -v -E "$F" | sed 's/^/old /')
  done
done
for run in "ant_pixels gru" "tmaze_10 trxl"; do
  set -- $run
  timeout 150 python3 cli.py train --env $1 --memory $2 --num-seeds 2 --total-steps 16384 --num-chunks 2 \
    --out $OUT_DIR/cli-$1-$2 2>&1 | grep -v -E "$F" | tail -n 2
  python3 -c "import json; s=json.load(open('$OUT_DIR/cli-$1-$2/summary.json')); print('$1 $2 compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
  rm -rf $OUT_DIR/cli-$1-$2
done
