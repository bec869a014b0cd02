"""Ctrl-C and `kill` while training: what `train` raises (`Interrupted`, naming the run directory to resume) and the
signal handling that turns either into it safely (`_CtrlC`)."""

import gc
import signal
import threading
from pathlib import Path


class Terminated(SystemExit):
    """A `kill` (SIGTERM: a scheduler's preemption) of the process running jobs side by side (`run_side_by_side`):
    its jobs ended, it exits with 128 + `signum` as the shell reports it, quietly from Python; the command line says
    how to continue."""

    def __init__(self, signum: int):
        super().__init__(128 + signum)
        self.signum = signum


class Interrupted(KeyboardInterrupt):
    """Training was interrupted (Ctrl-C, or a `kill`: `signum` is SIGINT or SIGTERM); `run_dir` is the run directory
    (None without one), `checkpoint` whether it holds a checkpoint (else `--resume` trains it from the start)."""

    def __init__(self, run_dir: Path | None, checkpoint: bool = False, signum: int = signal.SIGINT):
        super().__init__(str(run_dir))
        self.run_dir, self.checkpoint, self.signum = run_dir, checkpoint, int(signum)


class _CtrlC:
    """While training: Ctrl-C, or a `kill` (SIGTERM: a scheduler's preemption), raises KeyboardInterrupt at once and
    also sets `requested` (and `signum`), which the loop reads at every chunk boundary, so that the run directory is
    named with the command that resumes it. Inside a garbage-collection callback (JAX registers one) it only sets
    `requested`: Python would drop the exception there and print its traceback. Only in the main thread, over
    Python's own handlers (SIGINT's, and SIGTERM's default)."""

    def __init__(self):
        self.requested, self.signum, self.previous = False, signal.SIGINT, {}

    def _handle(self, signum, frame):
        self.requested, self.signum = True, signum
        if not _in_gc_callback(frame):
            raise KeyboardInterrupt

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for signum, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
                if signal.getsignal(signum) is default:
                    self.previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc):
        for signum, previous in self.previous.items():
            signal.signal(signum, previous)
        return False


def _in_gc_callback(frame) -> bool:
    """Whether `frame` runs inside one of `gc.callbacks`."""
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False
