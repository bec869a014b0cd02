#!/usr/bin/env bash
# Issue 9, compile time, round 2: the threefry kernel lowering, QR orthogonal initialisation, and the rollout's
# unroll apart from the GRU's. Usage: benchmarks/gpu_compile_probe2.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
B="python3 benchmarks/bench_compile.py --updates 40"
timeout 170 $B --cases tmaze_10:gru:30 --variants threefry=kernel orth=qr runroll=1 runroll=1,threefry=kernel,orth=qr \
  --json $OUT_DIR/compile2-tmaze.json 2>&1 | grep -v -E "$F"
timeout 200 $B --cases rocksample_11_11:gru:1 --variants runroll=1 runroll=2 threefry=kernel runroll=1,threefry=kernel,orth=qr \
  --json $OUT_DIR/compile2-rs.json 2>&1 | grep -v -E "$F" | tail -n +2
timeout 220 $B --cases battleship_10:gru:1 --variants runroll=1 runroll=2 threefry=kernel runroll=1,threefry=kernel,orth=qr \
  --json $OUT_DIR/compile2-bs.json 2>&1 | grep -v -E "$F" | tail -n +2
