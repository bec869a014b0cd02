#!/usr/bin/env bash
# Issue 9, session 11: the chunk's GEMMs split between cuBLAS (products over whole sequences) and Triton (products in
# sequential loops) for wide networks (`pobax.agent._train.CUBLAS_MIN_HIDDEN`, `pobax.memory._layers.split_gemms`),
# against XLA's default (`cublas=off`: Triton's GEMMs everywhere): compile, env steps/s and the chunk's GEMMs by
# backend, fresh processes, persistent cache off.
# (1) the 1-seed cases both ways (an even ROUND runs them in the other order), T-Maze as a control;
# (2) cross-process reproducibility: check_determinism.py in 5 processes at once per case (XLA_FLAGS as given);
# (3) the batched cases both ways.
# Usage: benchmarks/gpu_session11.sh OUTDIR [PARTS] [ROUND]
set -u
OUT_DIR=$(cd "${1:?output directory}" && pwd)
PARTS=${2:-12}
ROUND=${3:-1}
F="warp|UserWarning|warnings.warn|^$"
A=default; B=cublas=off
(( ROUND % 2 == 0 )) && { A=cublas=off; B=default; }
if [[ $PARTS == *1* ]]; then
  python3 benchmarks/bench_compile.py --kernels --cases battleship_10:gru:1 rocksample_11_11:gru:1 --variants $A $B \
    --json $OUT_DIR/split-round$ROUND.json 2>&1 | grep -vE "$F"
  python3 benchmarks/bench_compile.py --kernels --cases tmaze_10:gru:1 --json $OUT_DIR/split-control-round$ROUND.json \
    2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *2* ]]; then
  # 5 processes at once on the one GPU (the autotuner's timings under contention: where near ties flip)
  for c in ${DET_CASES:-battleship_10:gru:1 rocksample_11_11:gru:1}; do
    for i in 1 2 3 4 5; do
      (XLA_PYTHON_CLIENT_PREALLOCATE=false POBAX_COMPILE_CACHE=off python3 benchmarks/check_determinism.py --case $c \
        2>&1 | tail -1 | sed "s/^/$c process $i: /") &
    done
    wait
  done
fi
if [[ $PARTS == *3* ]]; then
  python3 benchmarks/bench_compile.py --kernels --cases battleship_10:gru:5 rocksample_11_11:gru:10 \
    rocksample_11_11:memoryless:8 --variants $A $B --json $OUT_DIR/split-batched-round$ROUND.json 2>&1 | grep -vE "$F"
fi
