#!/usr/bin/env bash
# Issue 9, alone on the GPU: (1) Battleship's reset without the rejection while_loop (LOOP_FREE) vs with it;
# (2) the GRU scan's hand-written backward (SCAN_VJP manual vs JAX's autodiff) in training; (3) the associative GAE
# (GAE_METHOD associative vs sequential); (4) the recurrence alone at the replay shapes; (5) XLA flags against
# compile time. Usage: benchmarks/gpu_perf_vjp.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
timeout 150 python3 benchmarks/bench_battleship_reset.py 2>&1 | grep -v -E "$F"
timeout 240 python3 benchmarks/bench_train.py --cases battleship_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:5 \
  rocksample_11_11:gru:10 --updates 60 --scan-vjp manual autodiff --json $OUT_DIR/train-vjp.json 2>&1 | grep -v -E "$F"
timeout 100 python3 benchmarks/bench_train.py --cases tmaze_10:gru:30 battleship_10:gru:1 --updates 60 \
  --gae associative sequential --json $OUT_DIR/train-gae.json 2>&1 | grep -v -E "$F"
timeout 50 python3 benchmarks/bench_gru_kernel.py --shapes 1x8x128x512 1x8x128x256 --impls dot dot_ad reduce reduce_ad \
  --iters 50 --json $OUT_DIR/gru-vjp-kernel.json 2>&1 | grep -v -E "$F"
for flags in "--xla_gpu_autotune_level=0" "--xla_gpu_enable_triton_gemm=false"; do
  echo "XLA_FLAGS='$flags'"
  XLA_FLAGS="$flags" timeout 50 python3 benchmarks/bench_train.py --cases tmaze_10:gru:30 --updates 60 \
    2>&1 | grep -v -E "$F" | tail -n 1
done
