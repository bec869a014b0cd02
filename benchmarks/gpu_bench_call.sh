#!/usr/bin/env bash
# One GPU call of benchmarks (alone on the GPU, one after another): the suite for the issue-9 targets, the
# pixel MuJoCo environments, and Craftax. Usage: benchmarks/gpu_bench_call.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
timeout 330 python3 benchmarks/run_all.py --envs tmaze_10 rocksample_11_11 battleship_10 Navix-DMLab-Maze-01-v0 \
  --train-cases tmaze_10:gru:1 tmaze_10:gru:30 tmaze_10:memoryless:30 tmaze_10:trxl:1 rocksample_11_11:gru:1 \
  rocksample_11_11:gru:10 battleship_10:gru:1 battleship_10:gru:5 \
  --md "$OUT_DIR/run_all.md" --json "$OUT_DIR/run_all.json" 2>&1 | grep -v -E "$F"
timeout 90 python3 benchmarks/bench_pixels.py --envs halfcheetah_pixels ant_pixels --num-envs 1024 4096 2>&1 | grep -v -E "$F" | tee "$OUT_DIR/pixels.txt"
timeout 120 python3 benchmarks/bench_craftax.py --num-envs 1024 --resets pool 2>&1 | grep -v -E "$F" | tee "$OUT_DIR/craftax.txt"
