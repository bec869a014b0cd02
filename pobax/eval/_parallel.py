"""Independent trainings side by side: one process per job, each on one device.

A program that does not fill a GPU (T-Maze: a few hundred small environments) runs no faster sharded over two GPUs
than on one, while such programs side by side, one per GPU, finish sooner (T-Maze's five agents 1.48× on four GPUs:
docs/performance.md, "Several devices"). `pobax benchmark` therefore trains its agents side by side on a machine
with several GPUs: each job is a fresh process (started with `spawn`, so that it initialises JAX itself) that sees
one device only, through `CUDA_VISIBLE_DEVICES` (and `HIP_VISIBLE_DEVICES`), and writes its output into its own log
file.
"""

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ._interrupt import Terminated


@dataclass(frozen=True)
class Job:
    """One training: `fn(*args)` in a process of its own, its output in `log`, started once the jobs labelled
    `after` have finished."""

    label: str
    fn: Callable
    args: tuple
    log: Path
    after: tuple[str, ...] = ()


def holds_gpu_memory(devices: list) -> bool:
    """Whether this process took most of its GPUs' memory when JAX started (its default preallocation), memory that
    jobs in other processes would then lack."""
    preallocate = os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", "true").lower() not in ("false", "0") and \
        os.environ.get("XLA_PYTHON_CLIENT_ALLOCATOR", "").lower() != "platform"  # the platform allocator: none
    return preallocate and any(d.platform == "gpu" for d in devices)


def default_jobs(devices: list) -> int:
    """Side by side on a machine with several GPUs (one job per GPU), else one job; one job also where this process
    holds the GPUs' memory (`holds_gpu_memory`)."""
    several_gpus = len(devices) > 1 and all(d.platform == "gpu" for d in devices)
    return len(devices) if several_gpus and not holds_gpu_memory(devices) else 1


def slot_environment(devices: list, jobs: int) -> list[dict[str, str]]:
    """The environment variables of each of `jobs` slots: slot k sees device k mod len(devices) alone (GPUs); the
    slots of a shared GPU allocate its memory as they need it instead of taking most of it up front.

    A device's index counts within what this process sees: under `CUDA_VISIBLE_DEVICES=1,2,3` JAX's GPU 0 is the
    machine's GPU 1, and a job told `CUDA_VISIBLE_DEVICES=0` would land on a GPU this process was kept off."""
    slots = []
    for k in range(jobs):
        d = devices[k % len(devices)]
        env: dict[str, str] = {}
        if d.platform == "gpu":
            index = getattr(d, "local_hardware_id", None)
            index = int(d.id if index is None else index)
            env = {var: _visible(var, index) for var in ("CUDA_VISIBLE_DEVICES", "HIP_VISIBLE_DEVICES")}
            if jobs > len(devices):
                env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
        slots.append(env)
    return slots


def _visible(var: str, index: int) -> str:
    """The value of `var` (`CUDA_VISIBLE_DEVICES`) that shows a job this process's GPU `index` alone."""
    visible = [v.strip() for v in os.environ.get(var, "").split(",") if v.strip()]
    return visible[index] if index < len(visible) else str(index)


@contextlib.contextmanager
def _environ(values: dict[str, str]):
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _die_with_parent(parent: int) -> None:
    """End this job's process when the process that started it (`parent`) ends, however it ends: a SIGKILL, which
    that process cannot catch to end its jobs itself, included. On Linux the kernel does it (PR_SET_PDEATHSIG);
    elsewhere a thread polls for the parent."""
    if sys.platform.startswith("linux"):
        import ctypes  # noqa: PLC0415

        try:
            if ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0:  # 1: PR_SET_PDEATHSIG
                if os.getppid() != parent:  # it ended before the call
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="pobax-parent-watch").start()


def _run_job(fn: Callable, args: tuple, log: str, parent: int | None = None) -> None:
    """The body of a job's process: its standard output and error into `log`, a failure's traceback there too; it
    ends with `parent` (the pid of the process that started it)."""
    if parent is not None:
        _die_with_parent(parent)
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    try:
        fn(*args)
    except BaseException:
        traceback.print_exc()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)
    sys.stdout.flush()
    sys.stderr.flush()


def run_side_by_side(jobs: list[Job], slots: list[dict[str, str]], progress: bool = True,
                     on_done: Callable[[Job], None] | None = None) -> list[Job]:
    """Run `jobs` in order, at most one per slot at a time (`slot_environment`): a free slot takes the first job
    whose `after` jobs have finished; `on_done(job)` after each success. Returns the jobs that failed (their logs
    say why) and those that waited on one that failed (not run). Ctrl-C (or any error here) ends the running jobs'
    processes: a checkpointed training resumes in the next call. A job's process also ends with this one when it is
    killed (`_die_with_parent`)."""
    ctx = multiprocessing.get_context("spawn")
    queue, failed, done = list(jobs), [], set()
    running: dict[int, tuple] = {}  # slot -> (process, job, start time)
    # A `kill` (SIGTERM: a scheduler's preemption, a shell's kill) ends the jobs too, as Ctrl-C does: Python's default
    # would end this process alone and leave its jobs training on, unwatched, into directories a rerun resumes.
    previous = None
    starting: list[bool] = []  # a job's process being started: a kill then waits until it is (`on_term`)
    pending: list[int] = []

    def on_term(signum, frame):
        if starting:  # interrupted there, the child would read half of what start() sends (a traceback from it)
            pending.append(signum)
        else:
            raise Terminated(signum)

    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, on_term)
    try:
        while queue or running:
            while stuck := [j for j in queue if {f.label for f in failed} & set(j.after)]:
                for job in stuck:
                    queue.remove(job)
                    failed.append(job)
                    if progress:
                        print(f"== not run: {job.label} (it waits on a job that failed)", flush=True)
            for k in range(len(slots)):
                ready = [j for j in queue if done.issuperset(j.after)]
                if k in running or not ready:
                    continue
                job = ready[0]
                queue.remove(job)
                job.log.parent.mkdir(parents=True, exist_ok=True)
                p = ctx.Process(target=_run_job, args=(job.fn, job.args, str(job.log), os.getpid()), daemon=False)
                starting.append(True)
                try:
                    with _environ(slots[k]):
                        p.start()
                    running[k] = (p, job, time.monotonic())
                finally:
                    starting.clear()
                if pending:
                    raise Terminated(pending[0])
                if progress:
                    where = slots[k].get("CUDA_VISIBLE_DEVICES")
                    print(f"== started {job.label}" + (f" on GPU {where}" if where is not None else "")
                          + f" (log: {job.log})", flush=True)
            if not running:  # what is left waits on jobs that are not in the queue
                failed.extend(queue)
                if progress:
                    print(f"== not run: {', '.join(j.label for j in queue)} (they wait on jobs not given)", flush=True)
                queue.clear()
                continue
            multiprocessing.connection.wait([p.sentinel for p, _, _ in running.values()])
            for k, (p, job, t0) in list(running.items()):
                if p.exitcode is None:
                    continue
                p.join()
                del running[k]
                took = f"{time.monotonic() - t0:.0f} s"
                if p.exitcode == 0:
                    done.add(job.label)
                    if progress:
                        print(f"== finished {job.label} in {took}", flush=True)
                    if on_done is not None:
                        on_done(job)
                else:
                    failed.append(job)
                    if progress:
                        print(f"== FAILED {job.label} after {took} (exit code {p.exitcode}): see {job.log}",
                              flush=True)
    finally:
        for p, _, _ in running.values():
            p.kill()  # at once: a job would take a SIGTERM only between two of its device calls (`train`)
        for p, _, _ in running.values():
            p.join()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return failed

