#!/usr/bin/env bash
# Issue 9, compile time, session 6: XLA's per-pass timers for one compile of each case (logs gzipped to OUTDIR,
# summarised by benchmarks/xla_pass_times.py), then the A/B of gpu_compile_parallel.sh for more cases.
# Usage: benchmarks/gpu_compile_passes.sh OUTDIR "CASES" "AB_CASES"
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"tmaze_10:gru:30 tmaze_10:gru:1"}
AB=${3:-"battleship_10:gru:1 tmaze_10:gru:1"}
export PYTHONUNBUFFERED=1
for c in $CASES; do
  n=$(echo $c | tr ':' '_')
  TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=hlo_pass_pipeline=1,gpu_compiler=1,nvptx_compiler=1,gemm_fusion_autotuner=1,autotuner_util=1 \
    timeout 120 python3 benchmarks/bench_compile.py --child $c default --updates 40 > $OUT_DIR/passes-$n.out 2> $OUT_DIR/passes-$n.err
  tail -n 1 $OUT_DIR/passes-$n.out | cut -c1-300
  gzip -f $OUT_DIR/passes-$n.err; python3 benchmarks/xla_pass_times.py $OUT_DIR/passes-$n.err.gz
done
benchmarks/gpu_compile_parallel.sh $OUT_DIR "$AB" 1
