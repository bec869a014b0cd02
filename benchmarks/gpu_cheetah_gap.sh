#!/usr/bin/env bash
# Issue 5 on one GPU: (A) the HalfCheetah-V gap at 2M steps, 5 seeds × 64 envs, normalised, its three agents
# (floor, GRU on V, ceiling GRU on F) trained side by side by `gap --only`, then assembled by a last `gap`;
# (B) Walker-V GRU at the paper's 4 envs per seed (5 seeds, 2M steps) to compare with the 64-env GRU of
# results/gap-walker-v-2M-h200.json. Usage: benchmarks/gpu_cheetah_gap.sh OUTDIR [LIMIT]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-540}
W=/tmp/cheetah; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.22
G="python3 cli.py gap --env HalfCheetah-V-v0 --total-steps 2000000 --num-seeds 5 --num-envs 64 --normalize-obs --normalize-reward --out $W/gap"
for a in floor gru ceiling; do timeout $LIMIT $G --only $a > $W/$a.log 2>&1 & done
timeout $LIMIT python3 cli.py train --env Walker-V-v0 --preset paper --memory gru --total-steps 2000000 --num-seeds 5 \
  --num-envs 4 --normalize-obs --normalize-reward --quiet --out $W/walker-gru-4envs > $W/walker4.log 2>&1 &
wait
timeout 120 $G > $W/gap.log 2>&1
cd $W && tar czf "$OUT_DIR/cheetah.tgz" *.log gap/gap.json gap/gap.png gap/*/summary.json gap/*/metrics.csv \
  gap/*/config.json walker-gru-4envs/summary.json walker-gru-4envs/metrics.csv walker-gru-4envs/config.json gap/*/metrics/*.csv walker-gru-4envs/metrics/*.csv 2>/dev/null
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$|^\["
for f in $W/*.log; do echo "=== $f"; grep -v -E "$F" "$f" | tail -n 12; done
