#!/usr/bin/env bash
# Issue 9, session 9: RockSample's cold compile once more.
# (1) which autotuning-related options this XLA knows (names in the CUDA plugin's library);
# (2) RockSample GRU 1 seed, one fresh compile with the GEMM autotuner's log (timestamps and threads: are the
#     candidates compiled in parallel?) and the dot shapes it tuned;
# (3) bench_compile A/B of options from (1) that would shrink the autotuner's search (only those this XLA knows).
# (4) training throughput of seeds × the paper's hyperparameter grid (`Nxgrid` cases: N seeds of each of the 24
#     sets of `pobax.eval.PAPER_GRID`, one program) next to seeds alone, for the issue's three environments.
# (5) one update's time, FLOPs, memory traffic and kernels (`profile_update.py` with `hlo_traffic.py`).
# (6) every GEMM to cuBLAS (`--xla_gpu_enable_triton_gemm=false`) against the default: compile and throughput.
# Usage: benchmarks/gpu_session9.sh OUTDIR [PARTS]   (PARTS: any of 123456, default 123)
set -u
OUT_DIR=$(cd "${1:?output directory}" && pwd)
PARTS=${2:-123}
F="warp|UserWarning|warnings.warn|^$"
if [[ $PARTS == *1* ]]; then
  SO=$(python3 -c "import jax_plugins, os, glob; print(' '.join(f for p in jax_plugins.__path__ for f in glob.glob(os.path.join(p, '*', '*.so'))))")
  echo "plugin libraries: $SO"
  strings $SO | grep -oE '^xla_gpu_[a-z0-9_]+$' | sort -u > $OUT_DIR/xla-gpu-options.txt
  echo "options: $(wc -l < $OUT_DIR/xla-gpu-options.txt)"
  grep -E 'autotun|triton|split_k|tma|warp_spec|parallel|cublas|gemm' $OUT_DIR/xla-gpu-options.txt | tr '\n' ' '; echo
fi
if [[ $PARTS == *2* ]]; then
  XLA_FLAGS="--xla_gpu_dump_autotune_logs_to=$OUT_DIR/autotune-rs.textproto" TF_CPP_MIN_LOG_LEVEL=0 \
    TF_CPP_VMODULE=hlo_pass_pipeline=1,gemm_fusion_autotuner=2,autotuner_compile_util=2,autotuner=2,autotuner_util=1 \
    POBAX_COMPILE_CACHE=off timeout 150 python3 benchmarks/bench_compile.py --child rocksample_11_11:gru:1 default \
    --updates 40 > $OUT_DIR/rs.out 2> $OUT_DIR/rs.err
  grep ROW $OUT_DIR/rs.out | cut -c1-400
  python3 benchmarks/xla_pass_times.py $OUT_DIR/rs.err | head -3
  echo "autotuner log lines by thread (first/last timestamp, count):"
  grep -E 'autotun' $OUT_DIR/rs.err | awk '{print $3}' | sort | uniq -c | sort -rn | head -20
  grep -E 'autotun' $OUT_DIR/rs.err | awk '{print $2, $3, $4}' | head -3
  grep -E 'autotun' $OUT_DIR/rs.err | awk '{print $2, $3, $4}' | tail -3
  echo "tuned instructions (name, result, timed candidates):"
  python3 - "$OUT_DIR/autotune-rs.textproto" <<'PY'
import re, sys
for block in open(sys.argv[1]).read().split("instruction_profiles {")[1:]:
    m = re.search(r'hlo_text: "%(\S+) = (\S+)', block)
    print(" ", m.groups() if m else "?", len(re.findall(r"nanos: \d+", block)))
PY
  gzip -f $OUT_DIR/rs.err $OUT_DIR/autotune-rs.textproto
fi
if [[ $PARTS == *3* ]]; then
  V="default"
  for o in xla_gpu_enable_split_k_autotuning xla_gpu_experimental_enable_triton_tma \
           xla_gpu_experimental_enable_triton_warp_specialization xla_gpu_enable_cublaslt; do
    grep -qx "$o" $OUT_DIR/xla-gpu-options.txt && V="$V xla=--$o=false"
  done
  echo "variants: $V"
  timeout 400 python3 benchmarks/bench_compile.py --updates 40 --cases rocksample_11_11:gru:1 --variants $V default \
    --json $OUT_DIR/compile-rs-options.json 2>&1 | grep -v -E "$F"
fi
if [[ $PARTS == *4* ]]; then
  timeout 560 python3 benchmarks/bench_train.py --updates 40 --cases tmaze_10:gru:30 tmaze_10:gru:5xgrid \
    tmaze_10:gru:30xgrid rocksample_11_11:gru:10 rocksample_11_11:gru:5xgrid battleship_10:gru:5 \
    battleship_10:gru:5xgrid --json $OUT_DIR/train-grid.json 2>&1 | grep -v -E "$F"
fi
if [[ $PARTS == *5* ]]; then
  (cd "$(dirname "$0")" && timeout 550 python3 profile_update.py --cases tmaze_10:gru:30 tmaze_10:gru:1 \
    rocksample_11_11:gru:1 battleship_10:gru:1 --iters 10 --peak-tflops 67 --peak-gbs 4800 \
    --json $OUT_DIR/profile-traffic.json 2>&1 | grep -v -E "$F")
fi
if [[ $PARTS == *6* ]]; then
  timeout 250 python3 benchmarks/bench_compile.py --updates 40 --cases rocksample_11_11:gru:1 --variants default \
    xla=--xla_gpu_enable_triton_gemm=false default xla=--xla_gpu_enable_triton_gemm=false \
    --json $OUT_DIR/tg-rs1.json 2>&1 | grep -v -E "$F"
  timeout 330 python3 benchmarks/bench_compile.py --updates 40 --cases rocksample_11_11:gru:10 battleship_10:gru:1 \
    tmaze_10:gru:30 tmaze_10:gru:1 --variants default xla=--xla_gpu_enable_triton_gemm=false \
    --json $OUT_DIR/tg-others.json 2>&1 | grep -v -E "$F"
fi
