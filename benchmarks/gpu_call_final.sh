#!/usr/bin/env bash
# (A) issue 9: the fused Pallas GRU recurrence on the GPU — kernel micro-benchmark over warp counts, then T-Maze GRU
# training at 30 and 1 seeds, scan (dot) vs fused, alone on the GPU. (B) issue 3: RockSample GRU on partial and on
# perfect_memory at lr 2.5e-3, λ0 0.5 (the best cells of gpu_rocksample_sweep.sh at 1.2M steps), 6 seeds.
# Usage: benchmarks/gpu_call_final.sh OUTDIR [STEPS] [LIMIT_B]
set -u
OUT_DIR=${1:?output directory}; STEPS=${2:-3000000}; LIMIT=${3:-330}
export PYTHONUNBUFFERED=1
timeout 100 python3 benchmarks/bench_gru_kernel.py --shapes 30x1x128x32 30x4x128x32 30x4x128x64 --num-warps 0 1 2 4 --iters 50 --json $OUT_DIR/gru_kernel.json 2>&1 | grep -v -i warn
timeout 150 python3 benchmarks/bench_train.py --cases tmaze_10:gru:30 tmaze_10:gru:1 --gru dot fused --updates 200 \
  --json $OUT_DIR/train_fused.json 2>&1 | grep -v -i warn
W=/tmp/rsfinal; rm -rf $W; mkdir -p $W
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.4
T="python3 cli.py train --env rocksample_11_11 --memory gru --preset paper --total-steps $STEPS --num-seeds 6 --lr 2.5e-3 --lambda0 0.5 --num-chunks 10 --quiet"
for obs in partial perfect_memory; do timeout $LIMIT $T --observability $obs --out $W/$obs > $W/$obs.log 2>&1 & done
wait
cd $W && tar czf "$OUT_DIR/rsfinal.tgz" *.log */summary.json */config.json */metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; tail -n 3 "$f"; done
