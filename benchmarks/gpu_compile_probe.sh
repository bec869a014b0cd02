#!/usr/bin/env bash
# Issue 9: where the cold compile time of a training run goes on the GPU, and what each knob saves.
# Usage: benchmarks/gpu_compile_probe.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
B="python3 benchmarks/bench_compile.py --updates 40"
timeout 120 $B --cases tmaze_10:gru:30 rocksample_11_11:gru:1 battleship_10:gru:1 --kernels \
  --json $OUT_DIR/compile-default.json 2>&1 | grep -v -E "$F"
timeout 240 $B --cases tmaze_10:gru:30 --variants unroll=1 vjp=autodiff gru=dot "xla=--xla_gpu_autotune_level=0" \
  "xla=--xla_gpu_enable_command_buffer=" "xla=--xla_gpu_force_compilation_parallelism=16" \
  --json $OUT_DIR/compile-tmaze.json 2>&1 | grep -v -E "$F" | tail -n +2
timeout 200 $B --cases battleship_10:gru:1 rocksample_11_11:gru:1 --variants unroll=1 vjp=autodiff \
  "xla=--xla_gpu_autotune_level=0" --json $OUT_DIR/compile-bs-rs.json 2>&1 | grep -v -E "$F" | tail -n +2
