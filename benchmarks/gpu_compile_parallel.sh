#!/usr/bin/env bash
# Issue 9, compile time, session 6: the two programs compiled at the same time and GAE as one weighted sum
# (the defaults now) against the previous defaults (gae=associative, parallel=0), alternating, fresh processes.
# (The session's runs also had a variant keys=one, one key split per rollout step, since made the default.)
# Usage: benchmarks/gpu_compile_parallel.sh OUTDIR "CASES" [ROUNDS]
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"tmaze_10:gru:30 rocksample_11_11:gru:1"}
ROUNDS=${3:-2}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$"
OLD="gae=associative,parallel=0"
V=""
for i in $(seq $ROUNDS); do V="$V default $OLD"; done
timeout 560 python3 benchmarks/bench_compile.py --updates 40 --cases $CASES --variants $V \
  --json $OUT_DIR/compile-parallel.json 2>&1 | grep -v -E "$F"
