"""Run pobax commands detached on a GPU machine, in lanes, and bring their records back as one tarball.

For a machine that is lent in calls of minutes (a command's call ends, its detached processes go on until the machine
is given back): `start` launches the queue in a new session and returns; `wait` packs what the commands wrote every
`--every` seconds until `--seconds` have passed or every lane is done, so a call returns as soon as nothing is left,
and exits 1 when a command has ended with another status than 0; the tarball holds what `pobax benchmark --merge`
needs and nothing larger (records, finished sweep parts, logs; no models or checkpoints).

    python benchmarks/detached_queue.py start --state /tmp/q --queue QUEUE [--require-gpu H200 [--otherwise QUEUE2]]
    python benchmarks/detached_queue.py wait --state /tmp/q --seconds 540 --pack /tmp/pA /tmp/w50/gru --to $OUT/r.tgz \
        --checkpoints-to $OUT/ck.tgz
    python benchmarks/detached_queue.py status --state /tmp/q

QUEUE is a text file, one command per line as `LANE: COMMAND` (`#` starts a comment). Lanes run at once; a lane's
commands run one after another in the order given, each with `bash -c` from the directory `start` ran in, whatever
the previous one's exit status. A lane named by a number runs with CUDA_VISIBLE_DEVICES set to it (one GPU per lane;
set the variable in the command to override), and every command with XLA_PYTHON_CLIENT_PREALLOCATE=false, so that
lanes may share a GPU. STATE/status.json says where each command stands (pending, running, its exit status) and
STATE/LANE.log holds each lane's output. `--require-gpu NAME` starts nothing unless every GPU's name contains NAME: a
protocol record takes the device of each of its sweep's parts, and one of two device kinds stays out of the table;
with `--otherwise QUEUE2` a machine of another kind starts QUEUE2 instead (probes that any kind may train: their
records name the device), both queues checked before either starts.

Packing: for each directory given to `--pack` (a `pobax benchmark --out`), its benchmark.json and report, its agents'
records and sweep tables, and under runs/ every `config.json`, `summary.json`, `sessions.json` and log, and a sweep's or gap report's
marker and results (`pobax-sweep.json`, `best.json`, `sweep.json`; `pobax-gap.json`, `gap.json`); under the
directory's own name in the tarball (two directories of one name are refused); with `--metrics`, each run's metrics
CSVs too (`pobax plot --metric NAME` reads them; a sweep continued from the tarball reads its finished programs'). The state directory's logs and status go under `queue/`. Unpack it
here and merge: `tar xzf r.tgz -C D && pobax benchmark --merge D/pA --out ...`.

Several calls issued back to back (so the machine stays warm between them) may each find a fresh machine: one whose
start failed leaves the next call without the queue. Give every call the same command, which starts the queue only
where the state holds none: `[ -f /tmp/q/status.json ] || { SETUP && python benchmarks/detached_queue.py start
--state /tmp/q --queue QUEUE; }; python benchmarks/detached_queue.py wait --state /tmp/q ...` (`start` refuses a
state whose queue still runs).

Resuming on the next machine: `wait --checkpoints-to $OUT/ck.tgz` packs, once at the end, every run of the `--pack`
directories that is resumable (a checkpoint and no summary: cut by the call's end or the machine's), whole, while
their sizes sum to at most `--max-mib` (45; the runs that do not fit are named and stay); a tarball over 15 MiB
comes as pieces `ck.tgz.00`, `ck.tgz.01`, ... (the device returns files of at most 16 MiB, 64 MiB in all:
`cat ck.tgz.?? > ck.tgz` joins them). Unpack it into a carried folder; on the next machine copy it over the same
`--out` before `start` (`cp -r CARRY/ck/pA/. /tmp/pA/`) and the same command resumes those runs from their
checkpoints (exactly: `sessions.json` then names both machines).
"""

import argparse
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

#: The largest piece of the checkpoint tarball (`pack_checkpoints`): the device returns files of at most 16 MiB.
PIECE_BYTES = 15 * 2**20

#: Files of a benchmark output directory that go into the tarball (models and checkpoints stay): run records, and a
#: `pobax sweep`'s or `pobax gap`'s marker and results under runs/ (the marker is what lets the same command continue
#: the sweep on the next machine from its finished programs).
RECORD_NAMES = ("config.json", "summary.json", "sessions.json", "pobax-sweep.json", "pobax-gap.json", "best.json",
                "sweep.json", "gap.json")
TOP_NAMES = ("benchmark.json", "benchmark.md", "benchmark.csv")


class QueueError(Exception):
    """Bad input: the message says what is wrong."""


def parse_queue(text: str) -> dict[str, list[str]]:
    """{lane: [command, ...]} from `LANE: COMMAND` lines, in order; comments and blank lines skipped."""
    lanes: dict[str, list[str]] = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        lane, sep, command = line.partition(":")
        lane, command = lane.strip(), command.strip()
        if not sep or not lane or not command or not lane.replace("-", "").replace("_", "").isalnum():
            raise QueueError(f"queue line {number} is not `LANE: COMMAND` (LANE letters, digits, - or _): {line!r}")
        lanes.setdefault(lane, []).append(command)
    if not lanes:
        raise QueueError("the queue has no commands: give lines `LANE: COMMAND`.")
    return lanes


def _write_status(state: Path, status: dict) -> None:
    tmp = state / "status.json.tmp"
    tmp.write_text(json.dumps(status, indent=1))
    os.replace(tmp, state / "status.json")


def read_status(state: Path) -> dict:
    path = Path(state) / "status.json"
    if not path.is_file():
        raise QueueError(f"{state} holds no queue (no status.json): start one with `start --state {state}`.")
    try:
        status = json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError):
        status = None
    if not isinstance(status, dict) or not isinstance(status.get("lanes"), dict):
        raise QueueError(f"{path} is not a queue's status (damaged or edited): start the queue again with another "
                         f"--state.")
    return status


def new_status(lanes: dict[str, list[str]]) -> dict:
    """Every command pending: what `start` writes and the supervisor then keeps current."""
    return {"lanes": {lane: [{"command": c, "state": "pending"} for c in cmds] for lane, cmds in lanes.items()},
            "started": time.time(), "done": False}


def run_lanes(state: Path, status: dict, cwd: Path) -> None:
    """The supervisor: each lane's pending commands in order, lanes at once; status.json rewritten whenever a command
    starts or ends. Returns when every command is done."""
    running: dict[str, tuple[dict, subprocess.Popen, object]] = {}
    while True:
        changed = False
        for lane, cmds in status["lanes"].items():
            pending = next((c for c in cmds if c["state"] == "pending"), None)
            if lane in running or pending is None:
                continue
            env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
            if lane.isdigit():
                env["CUDA_VISIBLE_DEVICES"] = lane
            log = open(state / f"{lane}.log", "a")
            log.write(f"== {pending['command']}\n")
            log.flush()
            proc = subprocess.Popen(["bash", "-c", pending["command"]], cwd=cwd, env=env, stdout=log,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            running[lane] = (pending, proc, log)
            pending.update(state="running", began=time.time())
            changed = True
        for lane, (command, proc, log) in list(running.items()):
            rc = proc.poll()
            if rc is None:
                continue
            log.write(f"== exit {rc}\n")
            log.close()
            command.update(state="done", rc=rc, ended=time.time())
            del running[lane]
            changed = True
        status["done"] = all(c["state"] == "done" for cmds in status["lanes"].values() for c in cmds)
        if changed:
            _write_status(state, status)
        if status["done"]:
            return
        time.sleep(1)


def gpu_names() -> list[str] | None:
    """The names of the machine's NVIDIA GPUs (`nvidia-smi -L`: "GPU 0: NVIDIA H200 (UUID: ...)"), None where there
    is no nvidia-smi to ask."""
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    return [line.split(":", 1)[1].split(" (UUID", 1)[0].strip() for line in out.stdout.splitlines()
            if line.startswith("GPU ") and ":" in line]


def _read_queue(queue: Path) -> dict[str, list[str]]:
    try:
        text = Path(queue).read_text()
    except UnicodeDecodeError:
        raise QueueError(f"--queue {queue} is not UTF-8 text: give lines `LANE: COMMAND`.") from None
    return parse_queue(text)


def start(state: Path, queue: Path, require_gpu: str | None = None, otherwise: Path | None = None) -> None:
    """Validate the queue, then run the supervisor in a new session (it outlives this process) and return.
    `require_gpu`: start only where every GPU's name contains it (e.g. "H200"), so that a machine of another kind
    trains nothing (a protocol's sweep parts must share one device kind); there, `otherwise` (a second queue file,
    validated with the first before either starts) runs instead, so that the machine trains what any kind may; where
    nvidia-smi lists no GPU, nothing starts."""
    if otherwise is not None and require_gpu is None:
        raise QueueError("--otherwise runs where the GPUs are not --require-gpu's kind: give --require-gpu too.")
    names = gpu_names()  # asked once: the kind (`require_gpu`) and the count (numbered lanes)
    queues = {q: _read_queue(q) for q in (queue, otherwise) if q is not None}
    lanes = queues[queue]
    if require_gpu is not None:
        if not names or any(require_gpu not in name for name in names):
            kind = ', '.join(names) if names else 'none that nvidia-smi lists'
            if otherwise is None or not names:  # no GPU listed: --otherwise's GPU lanes would run on the CPU
                raise QueueError(f"--require-gpu {require_gpu!r}: this machine's GPUs are {kind}; nothing started"
                                 + (" (--otherwise starts only where nvidia-smi lists GPUs)." if otherwise else "."))
            print(f"--require-gpu {require_gpu!r}: this machine's GPUs are {kind}; starting --otherwise {otherwise}",
                  flush=True)
            lanes = queues[otherwise]
    gpus = None if names is None else len(names)
    missing = sorted(lane for lane in lanes if lane.isdigit() and gpus is not None and int(lane) >= gpus)
    if missing:  # CUDA_VISIBLE_DEVICES naming no GPU would leave JAX on the CPU, silently
        raise QueueError(f"lanes {', '.join(missing)} name GPUs this machine lacks (it has {gpus}): renumber them "
                         f"below {gpus} (lanes may share a GPU) or name them with letters.")
    state = Path(state)
    if (state / "status.json").is_file() and not read_status(state).get("done"):
        raise QueueError(f"{state} holds a queue that is still running: wait for it or give another --state.")
    state.mkdir(parents=True, exist_ok=True)
    _write_status(state, new_status(lanes))
    with open(state / "supervisor.log", "a") as log:
        subprocess.Popen([sys.executable, os.path.abspath(__file__), "_supervise", "--state", str(state)],
                         cwd=os.getcwd(), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                         start_new_session=True)
    print(f"started {sum(map(len, lanes.values()))} commands in {len(lanes)} lanes ({', '.join(lanes)}); "
          f"status: {state / 'status.json'}", flush=True)


def _members(root: Path, metrics: bool = False) -> list[Path]:
    """The files of a benchmark output directory that a merge needs (and the logs); with `metrics`, each run's
    `metrics.csv` and `metrics/*.csv` too (what `pobax plot --metric` reads, and a sweep continuing its finished
    programs)."""
    files = [root / n for n in TOP_NAMES if (root / n).is_file()]
    files += sorted(p for p in (root / "agents").rglob("*") if p.is_file()) if (root / "agents").is_dir() else []
    if (root / "runs").is_dir():
        files += sorted(p for p in (root / "runs").rglob("*")
                        if p.is_file() and (p.name in RECORD_NAMES or p.suffix == ".log"
                                            or (metrics and (p.name == "metrics.csv"
                                                             or p.parent.name == "metrics" and p.suffix == ".csv"))))
    return files


def check_to(to: Path) -> None:
    """A QueueError unless `to` can be written as the tarball: new, or a gzip file (an earlier pack's)."""
    to = Path(to)
    if to.is_dir():
        raise QueueError(f"--to {str(to)!r} is a directory: name the tarball (.tgz) to write.")
    if os.path.lexists(to):
        try:
            with open(to, "rb") as f:
                gzip = f.read(2) == b"\x1f\x8b"
        except OSError:
            gzip = False
        if not gzip:
            raise QueueError(f"--to {str(to)!r} holds another file (not a tarball this script wrote): pass another "
                             f"--to, or remove it.")
    if not to.parent.is_dir():
        raise QueueError(f"--to {str(to)!r}: its folder does not exist.")


def pack(dirs: list[Path], to: Path, state: Path | None = None, metrics: bool = False) -> int:
    """Write the tarball `to` (atomically: a reader never sees half of it); returns the number of files in it.
    `metrics`: each run's metrics CSVs too (a 50M-step masked-MuJoCo run of 5 seeds: about 1.7 MB)."""
    names = [Path(d).resolve().name for d in dirs]
    if len(set(names)) != len(names):
        raise QueueError(f"--pack directories must have different names (they name the tarball's folders): {names}")
    to = Path(to)
    tmp = to.with_name(to.name + ".part")
    count = 0
    with tarfile.open(tmp, "w:gz") as tar:
        for d, name in zip(map(Path, dirs), names):
            if not d.is_dir():
                continue  # not written yet
            for f in _members(d, metrics):
                try:
                    tar.add(f, arcname=f"{name}/{f.relative_to(d)}")
                    count += 1
                except FileNotFoundError:  # replaced while packing: the next pack has it
                    pass
        if state is not None and Path(state).is_dir():
            for f in sorted(Path(state).glob("*")):
                if f.is_file() and f.suffix in (".log", ".json"):
                    tar.add(f, arcname=f"queue/{f.name}")
                    count += 1
    os.replace(tmp, to)
    return count


def _resumable(root: Path) -> list[Path]:
    """The run directories under `root/runs` that an interrupted training left resumable (a checkpoint, no summary)."""
    runs = Path(root) / "runs"
    if not runs.is_dir():
        return []
    return sorted(p.parent for p in runs.rglob("checkpoint.json") if not (p.parent / "summary.json").exists())


def _staged_run(run: Path, stage: Path, tries: int = 3) -> Path | None:
    """A consistent copy of the run directory `run` under `stage` (its training may be writing the next checkpoint
    meanwhile): the copy's `checkpoint.json` names a checkpoint file of the SHA-256 it records. None if no copy in
    `tries` was consistent or the run vanished. (Only the state file against its manifest: this script stays free
    of pobax, whose version may differ from the archive that trained the run; the resume checks the rest.)"""
    for attempt in range(tries):
        dest = stage / f"try{attempt}"
        try:
            shutil.copytree(run, dest)
            meta = json.loads((dest / "checkpoint.json").read_text())
            digest = hashlib.sha256((dest / meta["file"]).read_bytes()).hexdigest()
        except (OSError, ValueError, KeyError, TypeError, shutil.Error):
            digest, meta = None, {}
        if digest is not None and digest == meta.get("sha256"):
            return dest
        shutil.rmtree(dest, ignore_errors=True)
        time.sleep(1.0)
    return None


def pack_checkpoints(dirs: list[Path], to: Path, max_bytes: int,
                     piece_bytes: int | None = None) -> tuple[list[str], list[str]]:
    """Write the tarball `to` (atomically) of every resumable run directory of `dirs`, whole (its checkpoint, metrics
    chunks, configuration and sessions; a consistent copy: `_staged_run`) with the directory's `benchmark.json`, so
    that the next machine resumes it instead of starting it again; runs are added in order while their sizes sum to
    at most `max_bytes` (what comes back from the machine is limited). A tarball over `piece_bytes` is cut into
    pieces `to.00`, `to.01`, ... of that size (`cat` them back together), so that no file is over the limit of a
    file that comes back. Returns the runs packed and the runs left out, as `NAME/path/in/dir`."""
    to = Path(to)
    for old in [to, *to.parent.glob(f"{to.name}.[0-9][0-9]")]:  # an earlier call's
        old.unlink(missing_ok=True)
    tmp = to.with_name(to.name + ".part")
    packed, left, total = [], [], 0
    with tempfile.TemporaryDirectory() as stage, tarfile.open(tmp, "w:gz") as tar:
        for d in map(Path, dirs):
            if not d.is_dir():
                continue
            name = d.resolve().name
            for i, run in enumerate(_resumable(d)):
                label = f"{name}/{run.relative_to(d)}"
                copy = _staged_run(run, Path(stage) / f"{name}-{i}")
                size = sum(f.stat().st_size for f in copy.rglob("*") if f.is_file()) if copy else 0
                if copy is None or total + size > max_bytes:
                    left.append(label)
                    continue
                tar.add(copy, arcname=label)
                total += size
                packed.append(label)
                shutil.rmtree(copy)
            if any(label.startswith(f"{name}/") for label in packed):  # what makes it a benchmark's --out
                for top in TOP_NAMES:
                    if (d / top).is_file():
                        tar.add(d / top, arcname=f"{name}/{top}")
    if piece_bytes is not None and tmp.stat().st_size > piece_bytes:
        with open(tmp, "rb") as whole:
            for i, piece in enumerate(iter(lambda: whole.read(piece_bytes), b"")):
                part = to.with_name(f"{to.name}.{i:02d}.part")
                part.write_bytes(piece)
                os.replace(part, to.with_name(f"{to.name}.{i:02d}"))
        tmp.unlink()
    else:
        os.replace(tmp, to)
    return packed, left


def summary(status: dict) -> str:
    lines = []
    for lane, cmds in status["lanes"].items():
        for c in cmds:
            where = c["state"] if c["state"] != "done" else f"exit {c['rc']}"
            if c.get("began"):
                where += f", {((c.get('ended') or time.time()) - c['began']) / 60:.1f} min"
            lines.append(f"lane {lane}: {where}: {c['command'][:110]}")
    return "\n".join(lines)


def wait(state: Path, seconds: float, every: float, dirs: list[Path], to: Path | None,
         metrics: bool = False, checkpoints_to: Path | None = None, max_bytes: int = 0) -> dict:
    """Pack every `every` seconds until `seconds` have passed or the queue is done; return status. The resumable runs'
    checkpoints (`checkpoints_to`) are packed once, at the end: they are what a later machine resumes from."""
    end = time.time() + seconds
    while True:
        status = read_status(state)
        if to is not None:
            pack(dirs, to, state, metrics)
        if status.get("done") or time.time() >= end:
            break
        time.sleep(max(0.0, min(every, end - time.time())))
    if checkpoints_to is not None:
        packed, left = pack_checkpoints(dirs, checkpoints_to, max_bytes, PIECE_BYTES)
        print(f"checkpoints packed: {', '.join(packed) or 'none'}" + (f"; left out (over --max-mib): "
                                                                        f"{', '.join(left)}" if left else ""))
    return status


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("start", help="launch the queue detached and return")
    s.add_argument("--state", type=Path, required=True, help="directory for status.json and the lanes' logs")
    s.add_argument("--queue", type=Path, required=True, help="text file of `LANE: COMMAND` lines")
    s.add_argument("--require-gpu", default=None, metavar="NAME",
                   help="start only where every GPU's name contains NAME (e.g. H200): one device kind per protocol")
    s.add_argument("--otherwise", type=Path, default=None, metavar="QUEUE",
                   help="with --require-gpu: the queue to start where the GPUs are of another kind")
    w = sub.add_parser("wait", help="pack every --every s until --seconds pass or the queue is done")
    w.add_argument("--state", type=Path, required=True)
    w.add_argument("--seconds", type=float, required=True)
    w.add_argument("--every", type=float, default=30.0)
    w.add_argument("--pack", type=Path, nargs="*", default=[], help="benchmark output directories to pack")
    w.add_argument("--to", type=Path, default=None, help="the tarball (.tgz) to write")
    w.add_argument("--metrics", action="store_true", help="pack each run's metrics CSVs too (for `pobax plot`)")
    w.add_argument("--checkpoints-to", type=Path, default=None,
                   help="at the end, a second tarball of the --pack directories' resumable runs, whole")
    w.add_argument("--max-mib", type=float, default=45.0,
                   help="the checkpointed runs' size limit (runs over it stay); the tarball comes in pieces of 15 MiB")
    k = sub.add_parser("pack", help="pack benchmark output directories once")
    k.add_argument("dirs", type=Path, nargs="+")
    k.add_argument("--to", type=Path, required=True)
    k.add_argument("--state", type=Path, default=None)
    k.add_argument("--metrics", action="store_true", help="pack each run's metrics CSVs too (for `pobax plot`)")
    t = sub.add_parser("status", help="where each command stands")
    t.add_argument("--state", type=Path, required=True)
    v = sub.add_parser("_supervise")  # the detached supervisor itself
    v.add_argument("--state", type=Path, required=True)
    args = p.parse_args(argv)
    try:
        if args.cmd == "start":
            start(args.state, args.queue, args.require_gpu, args.otherwise)
        elif args.cmd == "_supervise":
            run_lanes(args.state, read_status(args.state), Path.cwd())
        elif args.cmd == "pack":
            check_to(args.to)
            if missing := [str(d) for d in args.dirs if not Path(d).is_dir()]:
                raise QueueError(f"nothing to pack in {', '.join(map(repr, missing))}: not a directory.")
            print(f"packed {pack(args.dirs, args.to, args.state, args.metrics)} files into {args.to}")
        elif args.cmd == "status":
            print(summary(read_status(args.state)))
        else:
            if not (0 <= args.seconds < math.inf and 0 < args.every < math.inf and 0 < args.max_mib < 2**20):
                raise QueueError("--seconds must be a finite number of 0 or more, --every a finite one more than 0, "
                                 "--max-mib one in (0, 1048576).")
            if args.pack and args.to is None:
                raise QueueError("--pack needs --to, the tarball to write.")
            if args.to is not None:
                check_to(args.to)
            if args.checkpoints_to is not None and not args.pack:
                raise QueueError("--checkpoints-to needs --pack (the directories whose runs to pack).")
            status = wait(args.state, args.seconds, args.every, args.pack, args.to, args.metrics,
                          args.checkpoints_to, int(args.max_mib * 2**20))
            print(summary(status))
            print("queue done" if status.get("done") else "queue still running")
            failed = [(lane, c) for lane, cmds in status["lanes"].items() for c in cmds
                      if c["state"] == "done" and c["rc"] != 0]
            if failed:  # the tarball is written all the same: what the others trained comes back
                print(f"error: {len(failed)} command(s) failed: "
                      + "; ".join(f"lane {lane} exit {c['rc']}: {c['command'][:60]}" for lane, c in failed)
                      + f" (their output: {args.state}/LANE.log)", file=sys.stderr)
                return 1
    except (QueueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
