#!/usr/bin/env bash
# Third GPU call: Brax stability under random actions (alone on the GPU), then the RockSample and Battleship
# gap reports continued from the finished agents of the earlier calls (PREV). Usage: OUTDIR PREV [LIMIT]
set -u
OUT_DIR=${1:?output directory}; PREV=${2:?previous runs}; LIMIT=${3:-420}
W=/tmp/gapchecks; rm -rf $W; mkdir -p $W; cp -r "$PREV"/. $W/
export PYTHONUNBUFFERED=1
python3 benchmarks/brax_stability_check.py --num-envs 1024 --steps 3000 2>&1 | grep -v -i -E "warp|warn|settotalmass|^$" | tee $W/stability.log
python3 benchmarks/brax_stability_check.py --envs HalfCheetah-V-v0 --physics mjx mjx-newton-1-4 --num-envs 1024 --steps 3000 2>&1 | grep -v -i -E "warp|warn|settotalmass|^$" | tee -a $W/stability.log
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
run() { local name=$1; shift; timeout "$LIMIT" python3 cli.py gap --out $W/$name "$@" > $W/$name.log 2>&1 & }
run rocksample --env rocksample_11_11 --total-steps 2000000 --num-seeds 10
run battleship --env battleship_10 --total-steps 3000000 --num-seeds 8
wait
cd $W && tar czf "$OUT_DIR/gapchecks3.tgz" *.log */gap.json */gap.png */*/summary.json */*/metrics.csv */*/config.json */*/checkpoint.json 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v "^\[" "$f" | tail -n 9; grep "^\[" "$f" | tail -n 1; done
