#!/usr/bin/env bash
# Long `pobax` commands (benchmark, sweep) on a lent GPU machine (the device tool), across calls: each call may start
# one command (detached, from a frozen copy of the tree, so that later calls' copies of the working tree do not
# change code under a running process), waits, and copies back what finished. Several commands may share the GPU
# (XLA_PYTHON_CLIENT_PREALLOCATE=false unless PREALLOCATE=true): small programs leave most of it idle.
#
#   benchmarks/device_benchmark.sh start NAME WAIT_S -- CLI_ARGS...   start `pobax CLI_ARGS` (log /tmp/bench-NAME.log)
#   benchmarks/device_benchmark.sh wait WAIT_S                        wait, then report
#   benchmarks/device_benchmark.sh chain WAIT_S NAME "CLI_ARGS" [NAME "CLI_ARGS" ...]
#                                                                     start these one after another (each when the
#                                                                     one before has ended; CLI_ARGS split at spaces),
#                                                                     detached, on the caller's CUDA_VISIBLE_DEVICES
#   benchmarks/device_benchmark.sh until MAX_S                        wait until every started command has ended
#                                                                     (or MAX_S seconds of this call passed: keep
#                                                                     MAX_S plus what runs before it under the
#                                                                     call's timeout), then report
#
# Benchmark commands should write into --out /tmp/bench, or /tmp/bench-NAME for benchmarks started together (each
# call of `pobax benchmark` rewrites its --out's benchmark.json): the report packs every such directory's finished
# agents' records, to gather here with `pobax benchmark --merge DIR/bench DIR/bench-NAME ... --out results`.
#   (each mode ends with: the processes' last lines, $OUT/agents.tgz with every finished agent's record, $OUT/gaps.tgz
#   with the reports of `gap` commands written to --out /tmp/gap-NAME,
#   $OUT/logs.tgz with the commands' logs, and $OUT/unfinished.tgz.part-* with the run directories of agents not
#   finished yet, to resume elsewhere: `cat unfinished.tgz.part-* | tar xz -C DIR`, then carry DIR/bench/runs as
#   results-carry/runs, if it fits beside the wheels in what a call carries: a masked-MuJoCo checkpoint of 5 seeds ×
#   64 environments is 38 MB of MJX state, which does not compress; such an agent trains again from its start)
#
# Environment: POBAX_COMMIT (the commit of the tree, which travels without .git). Wheels in .whl are installed
# first: what the device's Python lacks (tyro, docstring-parser, typeguard, beartype; navix and the modules its
# package imports: distrax, rlax, tfp-nightly, dm-tree, gast, decorator, dm-env; memax for the memory zoo). navix also imports wandb at
# module level, which pobax never calls: an empty stand-in module is written when wandb is missing. Records from
# an earlier machine can be brought back by carrying them as results-carry/agents (unpacked into /tmp/bench/agents
# before a start), and unfinished run directories as results-carry/runs (into /tmp/bench/runs: they resume).
set -u
mode=$1; shift
# Installed once per machine, and again when the wheels carried differ from those installed (a warm machine).
wheels=$(ls .whl/*.whl 2>/dev/null | sort | tr '\n' ' ')
if [ ! -d /tmp/site ] || [ "$(cat /tmp/site/.wheels 2>/dev/null)" != "$wheels" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  echo "$wheels" > /tmp/site/.wheels
  if ! PYTHONPATH=/tmp/site python3 -c "import wandb" 2>/dev/null; then
    mkdir -p /tmp/site/wandb && : > /tmp/site/wandb/__init__.py && : > /tmp/site/wandb/util.py
  fi
fi
# PREALLOCATE=true keeps JAX's preallocation (75% of the GPU) for an agent that has a GPU to itself.
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=${PREALLOCATE:-false}
mkdir -p /tmp/bench
if [ -d results-carry/agents ] && [ ! -f /tmp/bench/.carried ]; then
  cp -rn results-carry/agents /tmp/bench/ && cp -n results-carry/benchmark.json /tmp/bench/ 2>/dev/null
  # Records without their benchmark.json: an empty one, or `pobax benchmark` refuses the directory as not its own.
  [ -f /tmp/bench/benchmark.json ] || echo '{"envs": [], "calls": []}' > /tmp/bench/benchmark.json
  [ -d results-carry/runs ] && cp -rn results-carry/runs /tmp/bench/
  touch /tmp/bench/.carried
fi
if [ "$mode" = start ]; then
  name=$1; wait_s=$2; shift 3  # NAME WAIT_S --
  code=/tmp/code-$name
  rm -rf "$code"; mkdir -p "$code"; cp -r cli.py pobax "$code"/
  (cd "$code" && setsid nohup python3 cli.py "$@" > /tmp/bench-$name.log 2>&1 &)
  echo "started $name: pobax $* (log /tmp/bench-$name.log)"
elif [ "$mode" = chain ]; then
  wait_s=$1; shift
  for ((i = 1; i <= $#; i += 2)); do
    code=/tmp/code-${!i}; rm -rf "$code"; mkdir -p "$code"; cp -r cli.py pobax "$code"/
  done
  # The waiting shell's command line holds "python3 cli.py", so `until` waits for the whole chain.
  setsid nohup bash -c 'while [ $# -gt 1 ]; do (cd /tmp/code-$1 && python3 cli.py $2 > /tmp/bench-$1.log 2>&1); shift 2; done' \
    chain "$@" > /dev/null 2>&1 &
  echo "chained: $* (logs /tmp/bench-NAME.log)"
else
  wait_s=$1
fi
if [ "$mode" = until ]; then
  # The pattern's brackets keep pgrep from matching this shell's own command line.
  while [ "$SECONDS" -lt "$wait_s" ] && pgrep -f "python3 cli[.]py" > /dev/null; do sleep 5; done
else
  sleep "$wait_s"
fi
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
for log in /tmp/bench-*.log; do echo "== $log"; grep -E "^== |Traceback|Error|error" "$log" | tail -4; tail -c 300 "$log"; echo; done
outs=$(cd /tmp && for d in bench bench-*; do [ -f "$d/benchmark.json" ] && echo "$d/agents $d/benchmark.json"; done)
[ -n "$outs" ] && tar czf "$OUT/agents.tgz" -C /tmp $outs 2>/dev/null
# Unfinished run directories up to 40 MB together (a Transformer-XL checkpoint holds every environment's memory
# window: hundreds of MB, more than comes back), in parts of 15 MB.
unfinished=$(cd /tmp && total=0; for d in bench/runs/*/*/ bench-*/runs/*/*/; do [ -d "$d" ] || continue; d=${d%/}
  [ -f "${d%%/runs/*}/agents/${d#*/runs/}.json" ] && continue; mb=$(du -sm "$d" | cut -f1)
  if [ $((total + mb)) -le 40 ]; then total=$((total + mb)); echo "$d"; else echo "not brought back ($mb MB): $d" >&2; fi
done)
[ -n "$unfinished" ] && tar czf - -C /tmp $unfinished | split -b 15m - "$OUT/unfinished.tgz.part-"
# `gap` commands (e.g. a sweep: `start NAME 0 -- gap --env ... --sweep --out /tmp/gap-NAME`): their reports, presets
# and run summaries (JSON, Markdown, figures under 2 MB; no checkpoints), in one archive.
gaps=$(cd /tmp && ls -d gap-* 2>/dev/null)
[ -n "$gaps" ] && (cd /tmp && find $gaps \( -name '*.json' -o -name '*.md' -o -name '*.png' \) -size -2M | tar czf "$OUT/gaps.tgz" -T -)
# One archive of the logs: at most 8 files come back from a call.
(cd /tmp && tar czf "$OUT/logs.tgz" bench-*.log 2>/dev/null)
ls /tmp/bench/agents/* /tmp/bench-*/agents/* 2>/dev/null
