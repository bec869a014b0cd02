#!/usr/bin/env bash
# Issue 9, session 12: T-Maze GRU 1 seed's cold start (the one compile target not reliably met).
# (1) one run's programs traced without the vmap over runs (`_train.SINGLE_RUN_UNBATCHED`, the default) against the
#     vmap (`single=vmap`), the three 1-seed cases, fresh processes, persistent cache off (an even ROUND: other order);
# (2) T-Maze 1 seed with XLA's pass timers, the autotuner's log and its results (what won), per variant;
# (3) T-Maze 1 seed under autotuner settings: no cuBLASLt candidates, autotune level 0, Triton's search space given
#     by a file of tilings (`xla_gpu_gemm_autotuner_override_file`; OVERRIDE, default: part 2's winners).
# (4) T-Maze 1 seed with Triton's tilings picked by XLA's cost model (`xla_gpu_experimental_cost_model_gemm_tiling_options`:
#     top=N keeps the N tilings it estimates fastest of each GEMM; with one, nothing is left to autotune), or from a
#     file of two tilings (part 2's two most frequent winners);
# (5) the other cases with COSTMODEL (default top=1) against XLA's autotuning.
# (6) narrow-network cases with Triton's search space given as a file of tilings (`xla_gpu_gemm_autotuner_override_file`,
#     a per-program option): two tilings, or one alone (nothing to autotune).
# (7) T-Maze 1 seed with one tiling: XLA's pass timers, then LLVM / ptxas settings on top; Transformer-XL T-Maze
#     1 seed (8 updates) with and without it.
# (8) the library (one tiling for one run of a narrow network: `_train.TILING_MAX_HIDDEN`) against XLA's autotuning
#     (`tiling=off`), alternating; then T-Maze GRU 1 seed in 5 processes at once (check_determinism.py).
# Usage: benchmarks/gpu_session12.sh OUTDIR [PARTS] [ROUND]
set -u
OUT_DIR=$(cd "${1:?output directory}" && pwd)
PARTS=${2:-123}
ROUND=${3:-1}
F="warp|UserWarning|warnings.warn|^$"
A=default; B=single=vmap
(( ROUND % 2 == 0 )) && { A=single=vmap; B=default; }
if [[ $PARTS == *1* ]]; then
  python3 benchmarks/bench_compile.py --cases ${CASES:-tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1} \
    --variants $A $B $A $B --json $OUT_DIR/single-round$ROUND.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *2* ]]; then
  i=0
  for v in default single=vmap; do
    i=$((i+1))
    XLA_FLAGS="--xla_gpu_dump_autotune_logs_to=$OUT_DIR/autotune-log-$i.textproto --xla_gpu_dump_autotune_results_to=$OUT_DIR/autotune-results-$i.textproto" \
      TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=hlo_pass_pipeline=1 POBAX_COMPILE_CACHE=off \
      timeout 120 python3 benchmarks/bench_compile.py --child tmaze_10:gru:1 "$v" --updates 40 > $OUT_DIR/passes-$i.out 2> $OUT_DIR/passes-$i.err
    echo "== $i: tmaze_10:gru:1 $v"
    grep ROW $OUT_DIR/passes-$i.out | python3 -c "import json,sys; r=json.loads(sys.stdin.read()[4:]); print({k: round(v, 2) for k, v in r['stages']['_chunk'].items()}, 'total', round(r['total_s'], 2), 'steps/s', round(r['steps_per_s']))"
    python3 benchmarks/xla_pass_times.py $OUT_DIR/passes-$i.err | tail -n +2 | head -2
    grep -E "Finished|RunBackend|llvm|ptx" $OUT_DIR/passes-$i.err | grep -iE "backend|compile module|ptx" | tail -4
    echo "autotuned:" $(grep -c instruction_profiles $OUT_DIR/autotune-log-$i.textproto) $(grep -o "backend: \w*" $OUT_DIR/autotune-log-$i.textproto | sort | uniq -c | tr '\n' ' ')
    python3 - $OUT_DIR/autotune-results-$i.textproto $OUT_DIR/override-$i.textproto <<'PY'
import collections, re, sys
text = open(sys.argv[1]).read()
print("results file:", len(text), "chars; head:", text[:600].replace("\n", " | "))
wins = collections.Counter(" ".join(b.split()) for b in re.findall(r"triton\s*\{([^{}]*)\}", text))
print("winning Triton tilings:", sum(wins.values()), "over", len(wins), "distinct")
for cfg, n in wins.most_common():
    print(f"  {n} x {cfg}")
with open(sys.argv[2], "w") as f:
    for cfg, _ in wins.most_common():
        f.write("config { " + cfg + " }\n")
PY
    gzip -f $OUT_DIR/passes-$i.err
  done
  (cd $OUT_DIR && tar -czf logs.tgz passes-* autotune-* && rm -f passes-* autotune-*)
fi
if [[ $PARTS == *3* ]]; then
  O=${OVERRIDE:-$OUT_DIR/override-1.textproto}
  head -1 $O > $OUT_DIR/override-top1.textproto
  NOLT=--xla_gpu_experimental_autotune_backends=CUDNN,TRITON,NATIVE_EMITTER,CUSTOM_KERNEL
  python3 benchmarks/bench_compile.py --cases tmaze_10:gru:1 --variants default "xla=$NOLT" \
    "xla=--xla_gpu_gemm_autotuner_override_file=$O" "xla=--xla_gpu_gemm_autotuner_override_file=$O $NOLT" \
    "xla=--xla_gpu_gemm_autotuner_override_file=$OUT_DIR/override-top1.textproto $NOLT" \
    "xla=--xla_gpu_autotune_level=0" default --json $OUT_DIR/autotune-variants.json 2>&1 | grep -vE "$F"
fi
CM=--xla_gpu_experimental_cost_model_gemm_tiling_options
if [[ $PARTS == *4* ]]; then
  head -2 ${OVERRIDE:-benchmarks/results/session12-override.textproto} > $OUT_DIR/override-top2.textproto
  python3 benchmarks/bench_compile.py --cases tmaze_10:gru:1 --variants default "xla=$CM=top=1" "xla=$CM=top=2" \
    "xla=$CM=top=1,top_from_default=1" "xla=--xla_gpu_experimental_cost_model_gemm_tiling_default=true" \
    "xla=--xla_gpu_gemm_autotuner_override_file=$OUT_DIR/override-top2.textproto" "xla=$CM=top=1" default \
    --json $OUT_DIR/costmodel-tmaze.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *5* ]]; then
  python3 benchmarks/bench_compile.py --cases ${CASES5:-rocksample_11_11:gru:1 battleship_10:gru:1 tmaze_10:gru:30} \
    --variants default "xla=${COSTMODEL:-$CM=top=1}" default "xla=${COSTMODEL:-$CM=top=1}" \
    --json $OUT_DIR/costmodel-cases.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *6* ]]; then
  T2=$OUT_DIR/tilings-2.textproto; TA=$OUT_DIR/tilings-a.textproto; TB=$OUT_DIR/tilings-b.textproto
  printf 'config { block_m: 16 block_n: 8 block_k: 16 num_stages: 1 num_warps: 2 num_ctas: 1 }\nconfig { block_m: 64 block_n: 32 block_k: 32 num_stages: 1 num_warps: 4 num_ctas: 1 }\n' > $T2
  printf 'config { block_m: 64 block_n: 32 block_k: 32 num_stages: 1 num_warps: 4 num_ctas: 1 }\n' > $TA
  printf 'config { block_m: 64 block_n: 8 block_k: 32 num_stages: 1 num_warps: 2 num_ctas: 1 }\n' > $TB
  O=--xla_gpu_gemm_autotuner_override_file
  python3 benchmarks/bench_compile.py --cases ${CASES6:-tmaze_10:gru:1 tmaze_10:gru:30 tmaze_10:gru:5xgrid tmaze_10:memoryless:30} \
    --variants default "xla=$O=$T2" "xla=$O=$TA" "xla=$O=$TB" default --json $OUT_DIR/tilings-cases.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *7* ]]; then
  TA=$OUT_DIR/tilings-a.textproto; O=--xla_gpu_gemm_autotuner_override_file=$TA
  printf 'config { block_m: 64 block_n: 32 block_k: 32 num_stages: 1 num_warps: 4 num_ctas: 1 }\n' > $TA
  XLA_FLAGS="$O --xla_gpu_dump_autotune_logs_to=$OUT_DIR/autotune-log-a.textproto" TF_CPP_MIN_LOG_LEVEL=0 \
    TF_CPP_VMODULE=hlo_pass_pipeline=1,gpu_compiler=1 POBAX_COMPILE_CACHE=off \
    timeout 120 python3 benchmarks/bench_compile.py --child tmaze_10:gru:1 default --updates 40 > $OUT_DIR/passes-a.out 2> $OUT_DIR/passes-a.err
  grep ROW $OUT_DIR/passes-a.out | cut -c1-400
  python3 benchmarks/xla_pass_times.py $OUT_DIR/passes-a.err | tail -n +2 | head -2
  grep -iE "gpu_compiler.cc" $OUT_DIR/passes-a.err | grep -iE "time|took|sec" | cut -c1-250 | tail -12
  echo "autotuned:" $(grep -c instruction_profiles $OUT_DIR/autotune-log-a.textproto 2>/dev/null) $(grep -o "backend: \w*" $OUT_DIR/autotune-log-a.textproto 2>/dev/null | sort | uniq -c | tr '\n' ' ')
  gzip -f $OUT_DIR/passes-a.err; rm -f $OUT_DIR/autotune-log-a.textproto $OUT_DIR/passes-a.out
  python3 benchmarks/bench_compile.py --cases tmaze_10:gru:1 --variants "xla=$O" "xla=$O --xla_llvm_disable_expensive_passes=true" \
    "xla=$O --xla_gpu_disable_gpuasm_optimizations=true" "xla=$O --xla_backend_optimization_level=1" default "xla=$O" \
    --json $OUT_DIR/tiling-codegen.json 2>&1 | grep -vE "$F"
  python3 benchmarks/bench_compile.py --updates 8 --cases tmaze_10:trxl:1 --variants default "xla=$O" \
    --json $OUT_DIR/tiling-trxl.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *8* ]]; then
  python3 benchmarks/bench_compile.py --kernels --cases tmaze_10:gru:1 --variants default tiling=off default tiling=off default \
    tiling=off --json $OUT_DIR/tiling-library.json 2>&1 | grep -vE "$F"
  python3 benchmarks/bench_compile.py --cases tmaze_10:memoryless:1 --variants default tiling=off default tiling=off \
    --json $OUT_DIR/tiling-library-memoryless.json 2>&1 | grep -vE "$F"
  for i in 1 2 3 4 5; do
    (XLA_PYTHON_CLIENT_PREALLOCATE=false POBAX_COMPILE_CACHE=off python3 benchmarks/check_determinism.py \
      --case tmaze_10:gru:1 2>&1 | tail -1 | sed "s/^/tmaze_10:gru:1 process $i: /") &
  done
  wait
fi
