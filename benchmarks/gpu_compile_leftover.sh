#!/usr/bin/env bash
# Issue 9, compile time: what is left at the current defaults — the random draws of the training program (upper
# bound: all of them as JAX's threefry kernel) and the parallel GAE. Usage: benchmarks/gpu_compile_leftover.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
timeout 400 python3 benchmarks/bench_compile.py --updates 40 --cases tmaze_10:gru:30 rocksample_11_11:gru:1 \
  --variants default threefry=kernel gae=sequential --json $OUT_DIR/compile-leftover.json 2>&1 | grep -v -E "$F"
