#!/usr/bin/env bash
# Issue 9, compile time: XLA's GEMM autotuning levels (4, the default, checks every candidate's results against a
# reference; lower levels skip buffer initialisation and checks; 0 does not autotune).
# Usage: benchmarks/gpu_compile_autotune.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
timeout 400 python3 benchmarks/bench_compile.py --updates 40 --cases tmaze_10:gru:30 battleship_10:gru:1 \
  --variants default "xla=--xla_gpu_autotune_level=1" "xla=--xla_gpu_autotune_level=2" default \
  --json $OUT_DIR/compile-autotune.json 2>&1 | grep -v -E "$F"
