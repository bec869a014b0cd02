#!/usr/bin/env bash
# Training checks of issues 3, 5, 7 and 8 on one GPU: six `pobax gap` reports run side by side (each is
# latency-bound; one GPU holds them all), each killed at LIMIT seconds. Learning results only: throughput
# figures printed here are shared-GPU figures, not benchmarks. Usage: benchmarks/gpu_gap_checks.sh OUTDIR [LIMIT]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-540}
mkdir -p "$OUT_DIR"; W=/tmp/gapchecks; rm -rf $W; mkdir -p $W
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.14 PYTHONUNBUFFERED=1
run() {  # name, args...
  local name=$1; shift
  timeout "$LIMIT" python3 cli.py gap --out $W/$name --quiet "$@" > $W/$name.log 2>&1 &
}
run tmaze_10     --env tmaze_10 --memories gru --total-steps 1000000 --num-seeds 10
run rocksample   --env rocksample_11_11 --total-steps 2000000 --num-seeds 10
run battleship   --env battleship_10 --total-steps 4000000 --num-seeds 8
run maze01       --env Navix-DMLab-Maze-01-v0 --total-steps 5000000 --num-seeds 3
run walker       --env Walker-V-v0 --total-steps 2000000 --num-seeds 5 --num-envs 64 --normalize-obs
run cheetah      --env HalfCheetah-V-v0 --total-steps 2000000 --num-seeds 5 --num-envs 64 --normalize-obs
wait
# gap.json/gap.png per report, each agent's summary and tidy metrics (run directories hold per-chunk files too)
cd $W && tar czf "$OUT_DIR/gapchecks.tgz" *.log */gap.json */gap.png */*/summary.json */*/metrics.csv */*/config.json 2>/dev/null
for f in $W/*.log; do echo "=== $f"; tail -n 12 "$f"; done
