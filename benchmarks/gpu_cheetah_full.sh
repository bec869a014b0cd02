#!/usr/bin/env bash
# Issue 5: HalfCheetah on the full observation (F), 2M steps, 5 seeds × 64 envs, normalised, next to the gap of
# gpu_cheetah_gap.sh (whose ceiling, a GRU on F with the paper's λ0 = 0.1, ended below the GRU on V at 2M):
# (a) memoryless on F (paper "full" row: lr 2.5e-4, λ0 0.1), (b) GRU on F with λ0 0.9 (the GRU-on-V value).
# Usage: benchmarks/gpu_cheetah_full.sh OUTDIR [LIMIT]
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-500}
W=/tmp/cheetahf; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
T="python3 cli.py train --env HalfCheetah-V-v0 --observability full --preset paper --total-steps 2000000 --num-seeds 5 --num-envs 64 --quiet"
timeout $LIMIT $T --memory memoryless --lr 2.5e-4 --lambda0 0.1 --out $W/mlp-f > $W/mlp-f.log 2>&1 &
timeout $LIMIT $T --memory gru --action-concat --lr 2.5e-4 --lambda0 0.9 --out $W/gru-f-l09 > $W/gru-f-l09.log 2>&1 &
wait
cd $W && tar czf "$OUT_DIR/cheetahf.tgz" *.log */summary.json */metrics.csv */config.json */metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "warp|UserWarning|warnings.warn|^$" "$f" | tail -n 6; done
for d in $W/*/; do python3 -c "
import json,sys; d=json.load(open('$d/summary.json')); s=d['sets'][0]['return']
print('$d', round(s['mean'],1), [round(s['ci_low'],1), round(s['ci_high'],1)], 'steps/s', round(d['steps_per_s']), 'compile', round(d['compile_s'],1))" 2>/dev/null; done
