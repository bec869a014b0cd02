#!/usr/bin/env bash
# The issue-9 experiments on one GPU (alone on it; ~20 minutes, so the device tool ran them as three calls):
# per-phase profile, XLA command buffers for whole while loops, unroll factors, the GRU's recurrent product,
# and the persistent compilation cache. Results: benchmarks/README.md ("Where the time goes").
# Usage: benchmarks/gpu_perf_probes.sh OUTDIR
set -u
OUT_DIR=${1:?output directory}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
cd benchmarks
python3 profile_update.py --cases tmaze_10:gru:30 battleship_10:gru:1 --iters 10 --peak-tflops 67 \
  --json "$OUT_DIR/profile.json" 2>&1 | grep -v -E "$F"
CB="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL"
for flags in "" "$CB"; do
  echo "=== XLA_FLAGS='$flags'"
  XLA_FLAGS="$flags" python3 bench_env.py --envs tmaze_10 --num-envs 8192 --unroll 1 4 8 16 --steps 1000 2>&1 | grep -v -E "$F"
  XLA_FLAGS="$flags" python3 bench_train.py --updates 100 \
    --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1 2>&1 | grep -v -E "$F"
done
python3 bench_train.py --updates 100 --gru dot reduce \
  --cases tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1 --json "$OUT_DIR/gru.json" 2>&1 | grep -v -E "$F"
python3 bench_train.py --updates 100 --cases tmaze_10:gru:30 rocksample_11_11:gru:10 battleship_10:gru:5 \
  --json "$OUT_DIR/train.json" 2>&1 | grep -v -E "$F"
python3 bench_train.py --updates 100 --unroll 8 --cases tmaze_10:gru:30 2>&1 | grep -v -E "$F"
cd ..
rm -rf /tmp/cc; for i in 1 2; do
  POBAX_COMPILE_CACHE=/tmp/cc python3 cli.py train --env tmaze_10 --memory gru --action-concat \
    --preset paper --num-seeds 30 --total-steps 200000 --quiet --out /tmp/cc-run$i > /dev/null 2>&1
  python3 -c "import json; s=json.load(open('/tmp/cc-run$i/summary.json')); print('cache run $i: compile_s', round(s['compile_s'], 2), 'steps/s', round(s['steps_per_s']))"
done
