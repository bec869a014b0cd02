#!/usr/bin/env bash
# Issue 9, compile time, round 4: the threefry kernel for the initialisation only (now the default), and XLA's
# autotuners. Usage: benchmarks/gpu_compile_probe4.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
B="python3 benchmarks/bench_compile.py --updates 40"
timeout 60 python3 benchmarks/check_init_threefry.py --cases tmaze_10:gru:3 battleship_10:gru:2 rocksample_11_11:gru:2 2>&1 | grep -v -E "$F"
timeout 300 $B --cases tmaze_10:gru:30 --variants default init=xla "xla=--xla_gpu_experimental_enable_fusion_autotuner=false" \
  "xla=--xla_gpu_autotune_level=0" "xla=--xla_gpu_enable_triton_gemm=false" orth=qr runroll=1 default \
  --json $OUT_DIR/compile4-tmaze.json 2>&1 | grep -v -E "$F"
timeout 180 $B --cases rocksample_11_11:gru:1 battleship_10:gru:1 --variants default \
  "runroll=1,xla=--xla_gpu_experimental_enable_fusion_autotuner=false" \
  --json $OUT_DIR/compile4-bs-rs.json 2>&1 | grep -v -E "$F" | tail -n +2
