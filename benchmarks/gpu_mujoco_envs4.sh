#!/usr/bin/env bash
# Issue 5: (A) env-only throughput of the four masked robots (V variants) at 2048 envs at the current physics pins;
# (B) Walker-V GRU at the paper's 4 envs per seed (16 seeds vmapped, 1M steps), to compare with the 64-env GRU of
# results/gap-walker-v-2M-h200.json at the same steps per seed. Usage: benchmarks/gpu_mujoco_envs4.sh OUTDIR [LIMIT_B]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-380}
export PYTHONUNBUFFERED=1
timeout 150 python3 benchmarks/bench_env.py --envs Walker-V-v0 HalfCheetah-V-v0 Ant-V-v0 Hopper-V-v0 --num-envs 2048 \
  --steps 200 --json $OUT_DIR/brax_env_2048.json 2>&1 | grep -v -i -E "warn|settotalmass"
timeout $LIMIT python3 cli.py train --env Walker-V-v0 --preset paper --memory gru --total-steps 1000000 --num-seeds 16 \
  --num-envs 4 --num-chunks 10 --quiet --out /tmp/walker4 2>&1 | grep -v -i -E "warn|settotalmass" | tail -n 6
cd /tmp && tar czf "$OUT_DIR/walker4.tgz" walker4/config.json walker4/summary.json walker4/metrics.csv walker4/metrics/*.csv 2>/dev/null
