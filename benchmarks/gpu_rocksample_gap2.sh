#!/usr/bin/env bash
# Issue 3: the RockSample(11, 11) gap at 4M of the paper's 5M steps with 10 seeds (one device call) and the registry's settings (floor:
# memoryless on partial; GRU on partial; ceiling: GRU on perfect_memory; the two GRU agents at lr 2.5e-3, λ0 0.3
# after gpu_rocksample_sweep2.sh), the three agents side by side by `gap --only`, then the report.
# Usage: benchmarks/gpu_rocksample_gap2.sh OUTDIR [LIMIT] [NUM_ENVS] [STEPS]   (defaults: 520 s, 8 envs (the
# paper's), 4M steps; `... OUT 420 32` gives every agent 32 envs per seed)
set -u
OUT_DIR=${1:?output directory}; LIMIT=${2:-520}; ENVS=${3:-8}; STEPS=${4:-4000000}
W=/tmp/rsgap2; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
G="python3 cli.py gap --env rocksample_11_11 --total-steps $STEPS --num-seeds 10 --num-envs $ENVS --out $W/gap"
for a in floor gru ceiling; do timeout $LIMIT $G --only $a --quiet > $W/$a.log 2>&1 & done
wait
timeout 45 $G > $W/gap.log 2>&1
cd $W && tar czf "$OUT_DIR/rsgap2.tgz" *.log gap/gap.json gap/gap.png gap/*/summary.json gap/*/config.json \
  gap/*/metrics/*.csv 2>/dev/null
cp $W/gap/gap.json $W/gap/gap.png "$OUT_DIR/" 2>/dev/null
for f in $W/*.log; do echo "=== $f"; grep -v -E "^$" "$f" | tail -n 8; done
