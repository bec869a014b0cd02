#!/usr/bin/env bash
# Issue 9, compile time, session 6: the library now against a previous commit's (session 6: e14ed8a; session 7:
# d57be96), extracted to .gapprev/ with
# `git archive COMMIT pobax benchmarks/bench_compile.py benchmarks/bench_train.py | tar -x -C .gapprev`,
# alternating new / old, fresh processes, persistent cache off. Usage: benchmarks/gpu_compile_session6.sh OUTDIR "CASES" [ROUNDS]
set -u
OUT_DIR=${1:?output directory}
CASES=${2:-"tmaze_10:gru:30 tmaze_10:gru:1 rocksample_11_11:gru:1 battleship_10:gru:1"}
ROUNDS=${3:-2}
export PYTHONUNBUFFERED=1
F="warp|UserWarning|warnings.warn|^$|^device|^case"
BASE=$PYTHONPATH
OLDPATH=${BASE/$PWD/$PWD\/.gapprev}
(cd .gapprev && PYTHONPATH=$OLDPATH python3 -c "import pobax; print(\"old pobax:\", pobax.__file__)")
for c in $CASES; do
  for i in $(seq $ROUNDS); do
    n=$(echo $c | tr ':' '_')
    PYTHONPATH=$BASE timeout 120 python3 benchmarks/bench_compile.py --updates 40 --cases $c --json $OUT_DIR/new-$n-$i.json 2>&1 | grep -v -E "$F" | sed 's/^/new /'
    (cd .gapprev && PYTHONPATH=$OLDPATH timeout 120 python3 benchmarks/bench_compile.py --updates 40 --cases $c \
      --json $OUT_DIR/old-$n-$i.json 2>&1 | grep -v -E "$F" | sed 's/^/old /')
  done
done
