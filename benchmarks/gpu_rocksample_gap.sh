#!/usr/bin/env bash
# Issue 3 on one GPU: the RockSample(11, 11) gap at the paper's settings (hidden 256, 8 envs, entropy 0.2, best
# hyperparameters) with the family's reward normalisation, its three agents (floor: memoryless on partial;
# GRU on partial; ceiling: GRU on perfect_memory) trained side by side by `gap --only` and assembled by a last
# `gap`. Usage: benchmarks/gpu_rocksample_gap.sh OUTDIR [STEPS] [SEEDS] [LIMIT]
set -u
OUT_DIR=${1:?output directory}; STEPS=${2:-5000000}; SEEDS=${3:-10}; LIMIT=${4:-520}
W=/tmp/rocksample; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
G="python3 cli.py gap --env rocksample_11_11 --total-steps $STEPS --num-seeds $SEEDS --out $W/gap"
for a in floor gru ceiling; do timeout $LIMIT $G --only $a > $W/$a.log 2>&1 & done
wait
timeout 60 $G > $W/gap.log 2>&1
cd $W && tar czf "$OUT_DIR/rocksample.tgz" *.log gap/gap.json gap/gap.png gap/*/summary.json gap/*/metrics.csv \
  gap/*/config.json gap/*/metrics/*.csv 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "^$|^\[" "$f" | tail -n 12; done
