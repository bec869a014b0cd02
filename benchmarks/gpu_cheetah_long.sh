#!/usr/bin/env bash
# Issue 5: the HalfCheetah-V gap at 5M steps, 10 seeds × 64 envs, normalised — longer than one device call, so
# the four trainings run detached (setsid) and later calls wait on them:
#   floor (memoryless on V), GRU on V, ceiling (GRU on F, the paper's λ0 0.1), and a GRU on F with λ0 0.9.
# `start` launches them (resuming from checkpoints carried in .cheetah/*.tgz, if any) and waits; `wait` waits;
# both stop waiting after WAIT seconds, copy every run directory (checkpoints included) to OUTDIR as one .tgz per
# agent (metrics, no checkpoints: they are too large to come back), and once every run is finished assemble the gap report (gap.json, gap.png).
# Usage: benchmarks/gpu_cheetah_long.sh start|wait OUTDIR [WAIT]
set -u
MODE=${1:?start or wait}; OUT_DIR=${2:?output directory}; WAIT=${3:-540}
W=${CHEETAH_DIR:-/tmp/cheetah5}; AGENTS="floor gru ceiling gru-f-l09"
COMMON=${CHEETAH_COMMON:-"--total-steps 5000000 --num-seeds 10 --num-envs 64 --normalize-obs --normalize-reward"}
G="python3 cli.py gap --env HalfCheetah-V-v0 $COMMON --out $W/gap"
T="python3 cli.py train --env HalfCheetah-V-v0 --observability full --preset paper --memory gru --action-concat \
  --lr 2.5e-4 --lambda0 0.9 $COMMON"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.22
if [ "$MODE" = start ]; then
  mkdir -p $W/gap
  for f in .cheetah/*.tgz; do [ -e "$f" ] && tar xzf "$f" -C $W/gap; done
  for a in $AGENTS; do
    if [ $a = gru-f-l09 ]; then
      if [ -e $W/gap/$a/checkpoint.json ]; then cmd="$T --resume $W/gap/$a"; else cmd="$T --out $W/gap/$a"; fi
    else cmd="$G --only $a"; fi
    [ -e $W/gap/$a/summary.json ] || setsid nohup bash -c "$cmd" > $W/$a.log 2>&1 < /dev/null &
  done
fi
F="warp|UserWarning|warnings.warn|settotalmass|Delay kernel|^$"
t0=$(date +%s)
while [ $(( $(date +%s) - t0 )) -lt $WAIT ] && pgrep -f "cli.py (gap|train) --env HalfCheetah" > /dev/null; do sleep 10; done
for a in $AGENTS; do
  echo "=== $a: $(grep -v -E "$F" $W/$a.log 2>/dev/null | tr '\r' '\n' | grep -v '^$' | tail -n 1)"
  [ -d $W/gap/$a ] && tar czf "$OUT_DIR/$a.tgz" --exclude=model.eqx --exclude="checkpoint*" -C $W/gap $a
done
if ! pgrep -f "cli.py (gap|train) --env HalfCheetah" > /dev/null; then
  $G > $W/assemble.log 2>&1; grep -v -E "$F" $W/assemble.log | tail -n 12
  cp $W/gap/gap.json $W/gap/gap.png "$OUT_DIR/" 2>/dev/null
fi
ls -la "$OUT_DIR"
