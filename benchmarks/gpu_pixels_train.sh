#!/usr/bin/env bash
# Issue 6 on a GPU (alone on it): Ant pixel rows (step+render vs step at 1024 envs), then a short ant_pixels
# training run with many seeds vmapped in one program (GRU, paper preset). Craftax: gpu_craftax_train.sh.
# Usage: benchmarks/gpu_pixels_train.sh OUTDIR [ANT_SEEDS] [ANT_STEPS]
set -u
OUT_DIR=${1:?output directory}; ANT_SEEDS=${2:-32}; ANT_STEPS=${3:-100000}
W=/tmp/pixtrain; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
timeout 80 python3 benchmarks/bench_pixels.py --envs ant_pixels --num-envs 1024 --steps 100 \
  --modes step+render step 2>&1 | grep -v -E "$F" | tee $W/ant_bench.log
timeout 300 python3 cli.py train --env ant_pixels --memory gru --action-concat --preset paper --num-seeds $ANT_SEEDS \
  --total-steps $ANT_STEPS --num-chunks 5 --out $W/ant-gru > $W/ant.log 2>&1
python3 cli.py results --root $W
cd $W && tar czf "$OUT_DIR/pixtrain.tgz" *.log */summary.json */metrics.csv */config.json */metrics/*.csv 2>/dev/null
for f in $W/ant.log; do echo "=== $f"; grep -v -E "$F" "$f" | tail -n 4; done
