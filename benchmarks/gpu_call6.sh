#!/usr/bin/env bash
# Two reports side by side on one GPU: (A) the maze-01 ceiling through the paper's FullImageCNN at the
# paper's 10M steps (its earlier run was cut at 6.8M); (B) the Walker-V gap (issue 5) at 2M steps, 5 seeds, 64 envs,
# normalised, reusing the finished memoryless floor of an earlier call (benchmarks/results/walker-v-floor-2M)
# and training the GRU (V) and the ceiling (GRU on F). Usage: benchmarks/gpu_call6.sh OUTDIR [LIMIT]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-560}
W=/tmp/call6; rm -rf $W; mkdir -p $W/walker
cp -r benchmarks/results/walker-v-floor-2M $W/walker/floor
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.45
timeout $LIMIT python3 cli.py train --env Navix-DMLab-Maze-01-v0 --preset paper --num-seeds 4 --total-steps 10000000 \
  --memory memoryless --observability full --encoder full_cnn --quiet --out $W/maze-ceiling-cnn > $W/maze.log 2>&1 &
timeout $LIMIT python3 cli.py gap --env Walker-V-v0 --total-steps 2000000 --num-seeds 5 --num-envs 64 \
  --normalize-obs --normalize-reward --out $W/walker > $W/walker.log 2>&1 &
wait
cd $W && tar czf "$OUT_DIR/call6.tgz" *.log */gap.json */gap.png */*/summary.json */*/metrics.csv */*/config.json \
  */*/metrics/*.csv */summary.json */metrics.csv */config.json */metrics/*.csv 2>/dev/null
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$|^\["
for f in $W/*.log; do echo "=== $f"; grep -v -E "$F" "$f" | tail -n 12; done
