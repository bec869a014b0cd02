#!/usr/bin/env bash
# Second GPU probe for issue 9 (alone on the GPU): per-phase profile of one update, the GRU's recurrent
# product as a GEMM or as a fused multiply-reduce, the CNN convolutions native vs patches + matmul (each
# compiled afresh), and env-only T-Maze at unroll 8. Usage: benchmarks/gpu_perf_probe2.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
cd benchmarks
timeout 150 python3 profile_update.py --cases tmaze_10:gru:30 battleship_10:gru:1 --iters 10 --peak-tflops 67 \
  --json "$OUT_DIR/profile.json" 2>&1 | grep -v -E "$F"
timeout 200 python3 bench_train.py --updates 100 --gru dot reduce \
  --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1 --json "$OUT_DIR/gru.json" 2>&1 | grep -v -E "$F"
timeout 120 python3 bench_train.py --updates 16 --conv native matmul \
  --cases Navix-DMLab-Maze-01-v0:memoryless:3:full --json "$OUT_DIR/conv.json" 2>&1 | grep -v -E "$F"
timeout 50 python3 bench_env.py --envs tmaze_10 --num-envs 8192 --unroll 8 --steps 1000 2>&1 | grep -v -E "$F"
