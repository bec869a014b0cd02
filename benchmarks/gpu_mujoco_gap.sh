#!/usr/bin/env bash
# Walker-V and HalfCheetah-V gap reports (issue 5) side by side on one GPU, with observation and reward
# normalisation and 64 envs per seed. Usage: benchmarks/gpu_mujoco_gap.sh OUTDIR [LIMIT] [STEPS]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-540}; STEPS=${3:-2000000}
W=/tmp/mujocogap; rm -rf $W; mkdir -p $W
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 PYTHONUNBUFFERED=1
for env in Walker-V-v0 HalfCheetah-V-v0; do
  timeout "$LIMIT" python3 cli.py gap --env $env --total-steps $STEPS --num-seeds 5 --num-envs 64 \
    --normalize-obs --normalize-reward --out $W/$env > $W/$env.log 2>&1 &
done
wait
cd $W && tar czf "$OUT_DIR/mujocogap.tgz" *.log */gap.json */gap.png */*/summary.json */*/metrics.csv */*/config.json 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "^\[|warp|warn|settotalmass|^$" "$f" | tail -n 8; grep "^\[" "$f" | tail -n 1; done
