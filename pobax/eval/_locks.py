"""Advisory locks (`flock`) between pobax processes: on a file (`lock_file`: evaluations into one directory, a
benchmark directory's shared files), on a directory (`lock_dir`: the process that trains a run), dropped by the system
however the holder ends."""

import contextlib
import os
import stat
from pathlib import Path

from ._files import CheckpointError


#: The file whose lock serialises the updates of a benchmark directory's shared files (`shared_files`).
SHARED_LOCK = ".benchmark.lock"


def lock_file(path: Path, *, wait: bool):
    """The open file `path` (created once, never replaced or removed: a lock on a file that a rename replaces would
    guard nothing) under an exclusive advisory lock (`flock`) that lasts until it is closed, or until the process
    ends, however it ends. `wait`: block until another holder lets go, else raise BlockingIOError. None where the
    system or file system has no such locks (unguarded)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NONBLOCK", 0), 0o666)  # (a FIFO: no wait to open)
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # (a FIFO or a device there: not seekable, not a lock pobax keeps)
        os.close(fd)
        raise CheckpointError(f"{str(path)!r} is not a regular file (a FIFO, device or socket), so not the lock file "
                              f"pobax keeps there: remove it.")
    handle = os.fdopen(fd, "rb+")
    return handle if _flock(handle.fileno(), wait, handle.close) else None


class _OpenDir:
    """An open directory (its descriptor), closed by `close` (which drops a `flock` on it)."""

    def __init__(self, fd: int):
        self.fd = fd

    def close(self) -> None:
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)


def lock_dir(path: Path, *, wait: bool):
    """The directory `path`, open, under an exclusive advisory lock (`flock`) as `lock_file`'s: a lock no file inside
    can take away (a lock file can be deleted, and the next process would lock a new one)."""
    opened = _OpenDir(os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)))
    return opened if _flock(opened.fd, wait, opened.close) else None


def _flock(fd: int, wait: bool, close) -> bool:
    """Lock `fd` exclusively (`wait`: block, else BlockingIOError, `close` called first); False (`close` called)
    where the system or file system has no such locks."""
    try:
        import fcntl  # noqa: PLC0415  (POSIX only)
    except ImportError:
        close()
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        close()
        raise
    except OSError:  # a file system without locks
        close()
        return False
    return True


@contextlib.contextmanager
def shared_files(out: Path):
    """Hold `out`'s shared files (benchmark.json and the results tables, which every process writing into `out`
    reads, changes and writes back) for this process: processes training other agents into one --out at once wait
    for each other here instead of writing over each other's calls and rows. A lock on `out/.benchmark.lock`
    (`lock_file`); not reentrant."""
    handle = lock_file(Path(out) / SHARED_LOCK, wait=True)
    try:
        yield
    finally:
        if handle is not None:
            handle.close()


def is_transient(name: str) -> bool:
    """Whether a file name in a benchmark directory is one of pobax's own passing files: the shared lock, or a
    temporary (`_new_temporary`, `writable_dir`) that a rename or unlink is about to end."""
    return name == SHARED_LOCK or (name.startswith(".") and name.endswith(".tmp"))
