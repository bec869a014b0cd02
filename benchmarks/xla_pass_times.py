"""Sum XLA's per-pass compile timers from a log, per compiling thread (one thread per program compiled at once).

    TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=hlo_pass_pipeline=1 python benchmarks/bench_compile.py \
        --child tmaze_10:gru:30 default 2> compile.log
    python benchmarks/xla_pass_times.py compile.log        # plain or gzipped

Prints, for each thread that spent at least 0.05 s in HLO passes, the total and the eight slowest passes (e.g.
`priority-fusion`: operator fusion; `config-assigner`: autotuning of GEMMs and fusions). LLVM and ptxas time is
not in these timers.
"""

import collections
import gzip
import re
import sys

PASS = re.compile(r"^I\d+ (\S+)\s+(\d+) hlo_pass_pipeline.cc:\d+\] HLO pass: (\S+) time: .*?\((\d+) us\)")


def summarise(path: str) -> None:
    per_thread: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    first: dict[str, str] = {}
    with (gzip.open(path, "rt", errors="replace") if path.endswith(".gz") else open(path, errors="replace")) as f:
        for line in f:
            m = PASS.match(line)
            if m:
                per_thread[m.group(2)][m.group(3)] += int(m.group(4)) / 1e6
                first.setdefault(m.group(2), m.group(1))
    print(f"== {path}")
    for tid, passes in sorted(per_thread.items(), key=lambda kv: -sum(kv[1].values())):
        total = sum(passes.values())
        if total >= 0.05:
            top = ", ".join(f"{k} {v:.2f}" for k, v in passes.most_common(8))
            print(f" thread {tid} (first pass {first[tid]}): {total:.2f} s: {top}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    for p in sys.argv[1:]:
        summarise(p)
