#!/usr/bin/env bash
# Maze 01 at the paper's budget (issue 8): floor (memoryless, partial), GRU (partial) and the ceiling
# (memoryless on the full agent-centric map) through the paper's FullImageCNN and through a flattened input,
# 10M steps, paper presets. The GRU runs beside the others (two processes on the GPU).
# Usage: benchmarks/gpu_maze01.sh OUTDIR [SEEDS] [STEPS] [LIMIT]
set -u
OUT_DIR=${1:?output directory}; SEEDS=${2:-4}; STEPS=${3:-10000000}; LIMIT=${4:-560}
W=/tmp/maze01; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.45
E=Navix-DMLab-Maze-01-v0
T="python3 cli.py train --env $E --preset paper --num-seeds $SEEDS --total-steps $STEPS --quiet"
timeout $LIMIT $T --memory gru --action-concat --out $W/gru > $W/gru.log 2>&1 &
( timeout $((LIMIT / 2)) $T --memory memoryless --observability full --out $W/ceiling-cnn > $W/ceiling-cnn.log 2>&1
  timeout $((LIMIT / 3)) $T --memory memoryless --observability full --encoder flatten --out $W/ceiling-flat > $W/ceiling-flat.log 2>&1
  timeout 120 $T --memory memoryless --out $W/floor > $W/floor.log 2>&1 ) &
wait
python3 cli.py results --root $W
python3 cli.py plot $W/floor $W/gru $W/ceiling-cnn $W/ceiling-flat --out $W/maze01.png
cd $W && tar czf "$OUT_DIR/maze01.tgz" *.log *.png */summary.json */metrics.csv */config.json */metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; tail -n 3 "$f"; done
