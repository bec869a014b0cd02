#!/usr/bin/env bash
# Second GPU call of the training checks (after benchmarks/gpu_gap_checks.sh ran out of time): the Brax
# stability check (brax_stability_check.py; the call itself ran an uncommitted precision-check script) and
# env-only throughput of the 4 robots at 2048 envs (alone on the GPU), then the gap reports continued from the
# first call's finished agents (PREV holds their run directories).
# Usage: benchmarks/gpu_gap_checks2.sh OUTDIR PREV [LIMIT]
set -u
OUT_DIR=${1:?output directory}; PREV=${2:?previous runs}; LIMIT=${3:-420}
W=/tmp/gapchecks; rm -rf $W; mkdir -p $W; cp -r "$PREV"/. $W/
export PYTHONUNBUFFERED=1
python3 benchmarks/brax_stability_check.py --envs HalfCheetah-V-v0 --num-envs 1024 --steps 3000 2>&1 | grep -v -i warp | tee $W/stability.log
python3 benchmarks/bench_env.py --envs Walker-V-v0 HalfCheetah-V-v0 Ant-V-v0 Hopper-V-v0 --num-envs 2048 --steps 200 2>&1 | grep -v -i warp | tee $W/brax_env.log
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.25
run() { local name=$1; shift; timeout "$LIMIT" python3 cli.py gap --out $W/$name "$@" > $W/$name.log 2>&1 & }
run rocksample --env rocksample_11_11 --total-steps 2000000 --num-seeds 10
run battleship --env battleship_10 --total-steps 3000000 --num-seeds 8
run maze01     --env Navix-DMLab-Maze-01-v0 --total-steps 5000000 --num-seeds 3
wait
cd $W && tar czf "$OUT_DIR/gapchecks2.tgz" *.log */gap.json */gap.png */*/summary.json */*/metrics.csv */*/config.json */*/checkpoint.json 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v "^\[" "$f" | tail -n 9; done
