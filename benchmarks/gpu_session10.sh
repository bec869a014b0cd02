#!/usr/bin/env bash
# Issue 9, session 10: the chunk program's GEMMs to cuBLAS where its rollout has no matrix product and the network is
# wide (`pobax.agent._train.CUBLAS_MIN_HIDDEN`), against XLA's default (Triton's GEMMs, `cublas=off`): compile and
# env steps/s, fresh processes, persistent cache off.
# (1) the cases where the rule applies, both ways, alternating; (2) cases where it must not apply (the GEMMs column
#     says which backend the chunk got).
# (3) $XLA_FLAGS wins over the rule: RockSample GRU 1 seed with --xla_gpu_enable_triton_gemm=true.
# Usage: benchmarks/gpu_session10.sh OUTDIR [PARTS] [ROUND]   (PARTS: any of 123, default 12; an even ROUND runs the
# variants of (1) in the other order)
set -u
OUT_DIR=$(cd "${1:?output directory}" && pwd)
PARTS=${2:-12}
ROUND=${3:-1}
F="warp|UserWarning|warnings.warn|^$"
VARIANTS="default cublas=off"
(( ROUND % 2 == 0 )) && VARIANTS="cublas=off default"
if [[ $PARTS == *1* ]]; then
  python3 benchmarks/bench_compile.py --cases rocksample_11_11:gru:1 rocksample_11_11:gru:2 rocksample_11_11:ld:1 \
    rocksample_11_11:memoryless:1 rocksample_11_11:memoryless:8 --variants $VARIANTS \
    --json $OUT_DIR/rule-round$ROUND.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *2* ]]; then
  python3 benchmarks/bench_compile.py --cases tmaze_10:gru:1 tmaze_10:gru:30 rocksample_11_11:gru:10 battleship_10:gru:1 \
    --json $OUT_DIR/controls.json 2>&1 | grep -vE "$F"
fi
if [[ $PARTS == *3* ]]; then
  python3 benchmarks/bench_compile.py --cases rocksample_11_11:gru:1 --variants "xla=--xla_gpu_enable_triton_gemm=true" \
    --json $OUT_DIR/xla-flags-win.json 2>&1 | grep -vE "$F"
fi
