#!/usr/bin/env bash
# Issue 9, compile time, session 6: GEMM-autotuning flags (small dots left to XLA's own emitter instead of
# autotuned Triton/cuBLAS GEMMs; no cuBLAS fallback), fresh processes; and XLA's pass timers of profile_update's
# three programs (rollout / rollout+GAE / update) for T-Maze GRU x 30. Usage: benchmarks/gpu_compile_flags.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
T5="xla=--xla_gpu_gemm_rewrite_size_threshold=100000"
T6="xla=--xla_gpu_gemm_rewrite_size_threshold=1000000"
FB="xla=--xla_gpu_cublas_fallback=false"
timeout 250 python3 benchmarks/bench_compile.py --updates 40 --cases tmaze_10:gru:30 \
  --variants default "$T5" "$T6" "$FB" default "$T5" "$T6" "$FB" --json $OUT_DIR/flags-tmaze30.json 2>&1 | grep -v -E "$F"
timeout 200 python3 benchmarks/bench_compile.py --updates 40 --cases battleship_10:gru:1 tmaze_10:gru:1 \
  --variants default "$T5" "$T6" --json $OUT_DIR/flags-bs-t1.json 2>&1 | grep -v -E "$F"
TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=hlo_pass_pipeline=1 timeout 100 python3 benchmarks/profile_update.py \
  --cases tmaze_10:gru:30 > $OUT_DIR/prof-passes.out 2> $OUT_DIR/prof-passes.err
tail -n 4 $OUT_DIR/prof-passes.out; gzip -f $OUT_DIR/prof-passes.err
