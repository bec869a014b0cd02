#!/usr/bin/env bash
# Issue 9, compile time, round 3: XLA's own timers for one T-Maze GRU x 30 compile, and parallel LLVM compilation.
# Usage: benchmarks/gpu_compile_probe3.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
B="python3 benchmarks/bench_compile.py --updates 40"
TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1,compile_module_to_llvm_ir=1,autotuner_compile_util=1,gemm_fusion_autotuner=1,hlo_pass_pipeline=1 \
  timeout 100 python3 benchmarks/bench_compile.py --child tmaze_10:gru:30 default --updates 40 > $OUT_DIR/vlog.out 2> $OUT_DIR/vlog.err
tail -n 1 $OUT_DIR/vlog.out | cut -c1-400
grep -E "took|ms|sec|Timer" $OUT_DIR/vlog.err | grep -v -E "$F" | sort | uniq -c | sort -rn | head -5
timeout 200 $B --cases tmaze_10:gru:30 --variants default "xla=--xla_gpu_enable_llvm_module_compilation_parallelism=true" \
  "xla=--xla_gpu_enable_llvm_module_compilation_parallelism=true --xla_gpu_force_compilation_parallelism=16" unroll=1 \
  --json $OUT_DIR/compile3-tmaze.json 2>&1 | grep -v -E "$F"
