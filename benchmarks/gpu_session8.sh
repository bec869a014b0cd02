#!/usr/bin/env bash
# Issue 9, session 8 (alone on the GPU; results in results/session8-h200.json, benchmarks/README.md "Session 8").
# (1) env-only: bench_env's lean harness (default) against the per-environment one, T-Maze at unroll 1 / 4 / 8;
# (2) the rollout's dense layers as multiply-sum (`REDUCE_MAX_WORK`, the default) against GEMMs (`dense=0`),
#     alternating, fresh processes, persistent cache off: compile time and training throughput;
# (3) T-Maze learning with both; (4) XLA's pass timers and autotuner log for RockSample with both.
# Usage: benchmarks/gpu_session8.sh OUTDIR [PARTS]   (PARTS: any of 1234, default all)
set -u
OUT_DIR=${1:?output directory}
PARTS=${2:-1234}
F="warp|UserWarning|warnings.warn|^$"
if [[ $PARTS == *1* ]]; then
  timeout 200 python3 benchmarks/bench_env.py --envs tmaze_10 --num-envs 8192 --unroll 1 4 8 --harness lean per_env \
    --repeats 3 --json $OUT_DIR/env-tmaze-unroll.json 2>&1 | grep -v -E "$F"
  timeout 300 python3 benchmarks/bench_env.py --envs tmaze_10 rocksample_11_11 battleship_10 --num-envs 1 1024 8192 \
    --harness lean per_env --repeats 3 --json $OUT_DIR/env.json 2>&1 | grep -v -E "$F"
fi
if [[ $PARTS == *2* ]]; then
  timeout 150 python3 benchmarks/bench_compile.py --updates 40 --cases rocksample_11_11:gru:1 \
    --variants default dense=0 default dense=0 --json $OUT_DIR/compile-rs1.json 2>&1 | grep -v -E "$F"
  timeout 300 python3 benchmarks/bench_compile.py --updates 40 \
    --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:10 battleship_10:gru:1 battleship_10:gru:5 \
    --variants default dense=0 --json $OUT_DIR/compile-others.json 2>&1 | grep -v -E "$F"
fi
if [[ $PARTS == *3* ]]; then
  timeout 120 python3 benchmarks/gru_impl_learning_check.py --impls auto --dense 0 default --seeds 10 --steps 1000000 \
    --json $OUT_DIR/learning-dense.json 2>&1 | grep -v -E "$F"
fi
if [[ $PARTS == *4* ]]; then
  "$(dirname "$0")/gpu_compile_autotuner_log.sh" "$OUT_DIR" "rocksample_11_11:gru:1@default rocksample_11_11:gru:1@dense=0"
fi
