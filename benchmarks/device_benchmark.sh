#!/usr/bin/env bash
# Long `pobax` commands (benchmark, sweep) on a lent GPU machine (the device tool), across calls: each call may start
# one command (detached, from a frozen copy of the tree, so that later calls' copies of the working tree do not
# change code under a running process), waits, and copies back what finished. Several commands may share the GPU
# (XLA_PYTHON_CLIENT_PREALLOCATE=false unless PREALLOCATE=true): small programs leave most of it idle.
# Keep the calls back to back (`until` to near the call's limit, the next call at once): the lent machine goes back
# after about 30 s without a call, and the detached commands die with it (2026-11-26: a 23-min agent lost at 13/20).
#
#   benchmarks/device_benchmark.sh start NAME WAIT_S -- CLI_ARGS...   start `pobax CLI_ARGS` (log /tmp/bench-NAME.log)
#   benchmarks/device_benchmark.sh wait WAIT_S                        wait, then report
#                                                                     (`wait 1` installs the wheels: run it first when a
#                                                                     call starts python3 itself, before any `start`;
#                                                                     2026-11-27 such processes died on `import tyro`)
#   benchmarks/device_benchmark.sh chain WAIT_S NAME "CLI_ARGS" [NAME "CLI_ARGS" ...]
#                                                                     start these one after another (each when the
#                                                                     one before has ended; CLI_ARGS split at spaces),
#                                                                     detached, on the caller's CUDA_VISIBLE_DEVICES
#   benchmarks/device_benchmark.sh until MAX_S                        wait until every started command has ended
#                                                                     (or MAX_S seconds of this call passed: keep
#                                                                     MAX_S plus what runs before it under the
#                                                                     call's timeout), then report
#   benchmarks/device_benchmark.sh save [DIR...]                      stop every started command and stash what
#                                                                     the next machine needs to resume (below);
#                                                                     DIRs (bench-NAME, gap-NAME): only those
#   benchmarks/device_benchmark.sh fetch K                            bring back stash parts K to K+3
#
# Across machines (a lease ends before a long agent does): `save` stops the commands (an agent loses at most the
# chunk since its last checkpoint), packs every /tmp/bench*/ directory's benchmark.json, finished agents' records
# and unfinished agents' run directories, and every /tmp/gap-*/ directory whole (a sweep resumes too), into
# /tmp/stash/stash.tgz.part-* (15 MiB each; a pixel Transformer-XL checkpoint is about 100 MB of weights and Adam
# moments, which do not compress) with stash.sha256, and brings
# back parts 0-3 and the checksum; `fetch 4`, `fetch 8`, ... bring back the rest (one call per 4 parts: at most
# 8 files come back from a call). Here, put them in folders of at most 60 MiB under results-carry/ (stash-1,
# stash-2, ...) and carry one or more folders per call of the next machine (the first call carries the wheels
# too: 64 MiB a call in all). Every call copies the parts carried in results-carry/stash-*/ to /tmp/stash-in and,
# once all are there and the checksum matches, unpacks them into /tmp (existing files kept): then `start` the
# same commands with the same --out, and they resume from their checkpoints. Calls after the first need not carry
# the wheels (installed in /tmp/site on the machine). Several agents are better stashed apart (`save bench-A`,
# its fetches, then `save bench-B`, ...; 2026-11-27: two Craftax agents made one 340 MB stash): carried as
# results-carry/stash-A-1, stash-A-2, ... and stash-B-1, ..., each stash is unpacked once its own parts are
# all there, so the first agent restarts while the second's parts are still travelling.
#
# Benchmark commands should write into --out /tmp/bench, or /tmp/bench-NAME for benchmarks started together (each
# call of `pobax benchmark` rewrites its --out's benchmark.json): the report packs every such directory's finished
# agents' records, to gather here with `pobax benchmark --merge DIR/bench DIR/bench-NAME ... --out results`.
#   (each mode but save and fetch ends with: the processes' last lines, $OUT/agents.tgz with every finished agent's
#   record, $OUT/gaps.tgz with the reports of `gap` commands written to --out /tmp/gap-NAME, and $OUT/logs.tgz with
#   the commands' logs; unfinished agents travel to another machine only through `save`)
#
# Environment: POBAX_COMMIT (the commit of the tree, which travels without .git). Wheels in .whl are installed
# first: what the device's Python lacks (tyro, docstring-parser, typeguard, beartype; navix and the modules its
# package imports: distrax, rlax, tfp-nightly, dm-tree, gast, decorator, dm-env; memax for the memory zoo). navix also imports wandb at
# module level, which pobax never calls: an empty stand-in module is written when wandb is missing. pobax imports
# brax and mujoco only for the MuJoCo families: for other runs leave the MuJoCo wheels (29 MB) out of .whl, so that
# the first call has room for a stash folder beside the wheels (2026-11-27: 13 MB of wheels + 46 MB of stash).
# Records from an earlier machine can be brought back by carrying them as results-carry/agents (unpacked into /tmp/bench/agents
# before a start); unfinished agents by `save` (above).
set -u
mode=$1; shift
# Installed once per machine, and again when the wheels carried differ from those installed (a warm machine).
wheels=$(ls .whl/*.whl 2>/dev/null | sort | tr '\n' ' ')
if [ -z "$wheels" ] && [ ! -d /tmp/site ]; then
  echo "no wheels carried and none installed on this machine: carry .whl in this machine's first call" >&2; exit 2
fi
if [ -n "$wheels" ] && { [ ! -d /tmp/site ] || [ "$(cat /tmp/site/.wheels 2>/dev/null)" != "$wheels" ]; }; then
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
  touch /tmp/bench/.carried
fi
# The output directories of `pobax benchmark` commands (under /tmp, relative to it).
bench_dirs() { (cd /tmp && for d in bench bench-*; do [ -f "$d/benchmark.json" ] && echo "$d"; done); }
# Stash parts carried from an earlier machine (see `save`): gathered over calls, unpacked once complete.
# A stash travels as folders results-carry/stash-K/ or results-carry/stash-NAME-K/ (K = 1, 2, ...): the folders of
# one name make one stash, gathered in /tmp/stash-in/stash[-NAME] and unpacked once complete, so that several
# stashes (one per agent) can be carried to one machine.
for d in results-carry/stash-*/; do
  [ -d "$d" ] || continue
  d=${d%/}; g=$(basename "$d"); g=${g%-*}
  [ -f "/tmp/stash-in/$g/.unpacked" ] || { mkdir -p "/tmp/stash-in/$g" && cp -n "$d"/stash.* "/tmp/stash-in/$g/" 2>/dev/null; }
done
for dir in /tmp/stash-in/*/; do
  [ -d "$dir" ] && [ ! -f "$dir/.unpacked" ] || continue
  if [ -f "$dir/stash.sha256" ] && (cd "$dir" && cat stash.tgz.part-* 2>/dev/null | sha256sum -c --status stash.sha256); then
    (cd "$dir" && cat stash.tgz.part-* | tar xz -C /tmp --skip-old-files) && touch "$dir/.unpacked"
    echo "$(basename "$dir") unpacked into /tmp: $(cd /tmp && ls -d bench*/runs/*/* gap-* 2>/dev/null | tr '\n' ' ')"
  else
    echo "$(basename "$dir"): $(ls "$dir" | grep -c part-) parts here; carry the rest (or stash.sha256)"
  fi
done
if [ "$mode" = fetch ]; then
  first=$1
  parts=$(ls /tmp/stash/stash.tgz.part-* 2>/dev/null)
  [ -n "$parts" ] || { echo "no stash on this machine: run save first" >&2; exit 2; }
  n=$(echo "$parts" | wc -l)
  [ "$first" -lt "$n" ] || { echo "no part $first: the stash has parts 0-$((n - 1))" >&2; exit 2; }
  echo "$parts" | tail -n +$((first + 1)) | head -4 | xargs -r cp -t "$OUT"
  echo "stash: parts $first-$((first + 3 < n - 1 ? first + 3 : n - 1)) of 0-$((n - 1)) brought back"
  exit 0
fi
if [ "$mode" = save ]; then
  pkill -f "python3 cli[.]py"
  for _ in $(seq 30); do pgrep -f "python3 cli[.]py" > /dev/null || break; sleep 1; done
  pkill -9 -f "python3 cli[.]py"; sleep 1
  rm -rf /tmp/stash && mkdir -p /tmp/stash
  # `save DIR...` stashes only these /tmp directories (bench-NAME, gap-NAME): one stash per agent, carried apart.
  only=" $* "
  wanted() { [ "$only" = "  " ] || [[ "$only" == *" $1 "* ]]; }
  keep=$(cd /tmp && for d in $(bench_dirs); do wanted "$d" || continue
    echo "$d/benchmark.json"
    [ -d "$d/agents" ] && echo "$d/agents"
    for r in "$d"/runs/*/*/; do [ -d "$r" ] || continue; r=${r%/}
      [ -f "$d/agents/${r#*/runs/}.json" ] || echo "$r"; done; done
    for d in gap-*; do [ -d "$d" ] && wanted "$d" && echo "$d"; done)
  [ -n "$keep" ] || { echo "nothing to stash (no /tmp/bench*/benchmark.json, no /tmp/gap-*)" >&2; exit 2; }
  (cd /tmp && tar czf - $keep) | split -b 15m - /tmp/stash/stash.tgz.part-
  (cd /tmp/stash && cat stash.tgz.part-* | sha256sum > stash.sha256)
  cp /tmp/stash/stash.sha256 "$OUT"/
  ls /tmp/stash/stash.tgz.part-* | head -4 | xargs cp -t "$OUT"
  n=$(ls /tmp/stash/stash.tgz.part-* | wc -l)
  echo "stashed $(du -sm /tmp/stash | cut -f1) MB in $n parts: $keep" | tr '\n' ' '; echo
  [ "$n" -gt 4 ] && echo "bring back the rest with: fetch 4$([ "$n" -gt 8 ] && echo ', fetch 8, ...')"
  exit 0
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
outs=$(for d in $(bench_dirs); do echo "$d/agents $d/benchmark.json"; done)
[ -n "$outs" ] && tar czf "$OUT/agents.tgz" -C /tmp $outs 2>/dev/null
# `gap` commands (e.g. a sweep: `start NAME 0 -- gap --env ... --sweep --out /tmp/gap-NAME`): their reports, presets
# and run summaries (JSON, Markdown, figures and learning curves (metrics.csv) under 2 MB; no checkpoints), in one archive.
gaps=$(cd /tmp && ls -d gap-* 2>/dev/null)
[ -n "$gaps" ] && (cd /tmp && find $gaps \( -name '*.json' -o -name '*.md' -o -name '*.png' -o -name metrics.csv \) -size -2M | tar czf "$OUT/gaps.tgz" -T -)
# One archive of the logs: at most 8 files come back from a call.
(cd /tmp && tar czf "$OUT/logs.tgz" bench-*.log 2>/dev/null)
ls /tmp/bench/agents/* /tmp/bench-*/agents/* 2>/dev/null
