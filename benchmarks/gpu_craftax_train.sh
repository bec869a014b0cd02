#!/usr/bin/env bash
# Issue 6 on a GPU (alone on it): a short craftax_pixels GRU run with seeds vmapped in one program (paper
# preset: hidden 512, 256 envs per seed, previous action as uint8 planes), with its achievement success rates.
# Usage: benchmarks/gpu_craftax_train.sh OUTDIR [SEEDS] [STEPS] [LIMIT]
set -u
OUT_DIR=${1:?output directory}; SEEDS=${2:-4}; STEPS=${3:-400000}; LIMIT=${4:-330}
W=/tmp/craftax; rm -rf $W; mkdir -p $W
export PYTHONUNBUFFERED=1
timeout $LIMIT python3 cli.py train --env craftax_pixels --memory gru --action-concat --preset paper \
  --num-seeds $SEEDS --total-steps $STEPS --num-chunks 4 --out $W/craftax-gru > $W/craftax.log 2>&1
grep -v -E "warp|warn" $W/craftax.log | tail -n 12
python3 - <<'PY'
import glob
import pandas as pd
m = pd.concat([pd.read_csv(f) for f in sorted(glob.glob("/tmp/craftax/craftax-gru/metrics/*.csv"))])
print("episodes ended per update (mean):", round(m["episodes"].mean(), 1), "| max steps reached:", m["env_step"].max())
last = m[m["update"] >= m["update"].max() - 3]
rates = last.filter(like="achievement_").mean().sort_values(ascending=False)
print("achievement success rates (last 4 updates, mean over seeds):")
print(rates[rates > 0].round(3).to_string())
PY
cd $W && tar czf "$OUT_DIR/craftax.tgz" craftax.log craftax-gru/config.json craftax-gru/metrics/*.csv craftax-gru/summary.json 2>/dev/null
