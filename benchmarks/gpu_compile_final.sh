#!/usr/bin/env bash
# Issue 9, compile time: the library's defaults now (threefry kernel + QR for the initialisation, one trace of the
# update, rollout not unrolled) against the previous ones (init=xla, orth=gram_schmidt, runroll=4), alternating, two
# of each, fresh processes. Usage: benchmarks/gpu_compile_final.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
OLD="init=xla,orth=gram_schmidt,runroll=4"
timeout 540 python3 benchmarks/bench_compile.py --updates 40 \
  --cases tmaze_10:gru:30 rocksample_11_11:gru:1 battleship_10:gru:1 --variants default $OLD default $OLD \
  --json $OUT_DIR/compile-final.json 2>&1 | grep -v -E "$F"
