#!/usr/bin/env bash
# GPU probe for issue 9 (one device call, alone on the GPU): (1) how the CNN encoders' convolutions are
# computed (native grouped convolutions under the seed vmap, or patches + batched matmul), (2) XLA command
# buffers (CUDA graphs) that take whole while loops, against the default flags, for training and env-only.
# Usage: benchmarks/gpu_perf_probe.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
timeout 170 python3 benchmarks/bench_train.py --cases Navix-DMLab-Maze-01-v0:memoryless:3:full ant_pixels:memoryless:16 \
  --conv native matmul --updates 16 --json "$OUT_DIR/conv.json" 2>&1 | grep -v -E "$F"
CB="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL"
for flags in "" "$CB"; do
  echo "=== XLA_FLAGS='$flags'"
  XLA_FLAGS="$flags" timeout 50 python3 benchmarks/bench_env.py --envs tmaze_10 --num-envs 8192 --unroll 1 4 16 \
    --steps 1000 2>&1 | grep -v -E "$F"
  XLA_FLAGS="$flags" timeout 130 python3 benchmarks/bench_train.py --updates 100 \
    --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1 2>&1 | grep -v -E "$F"
done
echo "=== XLA_FLAGS='$CB --xla_gpu_graph_min_graph_size=1'"
XLA_FLAGS="$CB --xla_gpu_graph_min_graph_size=1" timeout 60 python3 benchmarks/bench_train.py --updates 100 \
  --cases tmaze_10:gru:30 tmaze_10:gru:1 2>&1 | grep -v -E "$F"
