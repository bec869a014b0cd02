#!/usr/bin/env bash
# Issue 9, compile time, session 7: for each CASE@VARIANT, one fresh run with XLA's pass timers and the autotuner's
# log (what it tuned, with which backends), summarised; the logs in OUTDIR/logs.tgz. VARIANT as in bench_compile.py
# (XLA flags joined by +); VMODULE=... adds TF_CPP_VMODULE entries.
# Usage: benchmarks/gpu_compile_autotuner_log.sh OUTDIR "CASE@VARIANT ..."
set -u
OUT_DIR=${1:?output directory}
RUNS=${2:-"rocksample_11_11:gru:1@default"}
export PYTHONUNBUFFERED=1
i=0
for cv in $RUNS; do
  i=$((i+1)); c=${cv%%@*}; v=${cv#*@}; XF=""
  [[ $v == *xla=* ]] && XF=$(echo "${v#*xla=}" | tr '+' ' ')  # flags joined by + (the run list is split on spaces)
  XLA_FLAGS="--xla_gpu_dump_autotune_logs_to=$OUT_DIR/autotune-$i.textproto $XF" TF_CPP_MIN_LOG_LEVEL=0 \
    TF_CPP_VMODULE=hlo_pass_pipeline=1${VMODULE:+,$VMODULE} POBAX_COMPILE_CACHE=off \
    timeout 120 python3 benchmarks/bench_compile.py --child $c "$v" --updates 40 > $OUT_DIR/passes-$i.out 2> $OUT_DIR/passes-$i.err
  echo "== $i: $c $v"; grep ROW $OUT_DIR/passes-$i.out | python3 -c "import json,sys; r=json.loads(sys.stdin.read()[4:]); print({k: round(v, 2) for k, v in r['stages']['_chunk'].items()}, 'total', round(r['total_s'], 2), 'steps/s', round(r['steps_per_s']))"
  gzip -f $OUT_DIR/passes-$i.err; python3 benchmarks/xla_pass_times.py $OUT_DIR/passes-$i.err.gz | tail -n +2 | head -2
  echo "autotuned:" $(grep -c instruction_profiles $OUT_DIR/autotune-$i.textproto) $(grep -o "backend: \w*" $OUT_DIR/autotune-$i.textproto | sort | uniq -c | tr '\n' ' ')
  gzip -f $OUT_DIR/autotune-$i.textproto
done
(cd $OUT_DIR && tar -czf logs.tgz passes-* autotune-* 2>/dev/null && rm -f passes-* autotune-*)
