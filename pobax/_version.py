"""The package's version, and the commit of the code that produced a result (provenance of run directories)."""

import functools
import importlib.metadata
import os
import subprocess
from pathlib import Path

try:
    __version__ = importlib.metadata.version("pobax-bench")
except importlib.metadata.PackageNotFoundError:  # imported from a checkout that was not installed
    __version__ = "0+unknown"


@functools.cache
def commit() -> str:
    """`$POBAX_COMMIT` if set (e.g. on a machine that received a copy of the tree without its git history), else
    the checkout's `git` commit with `-dirty` when tracked files differ from it, else "unknown"."""
    if os.environ.get("POBAX_COMMIT"):
        return os.environ["POBAX_COMMIT"]
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return "unknown"
    try:
        run = lambda *a: subprocess.run(["git", "-C", str(root), *a], capture_output=True, text=True, timeout=10)  # noqa: E731
        head = run("rev-parse", "--short=12", "HEAD")
        if head.returncode:
            return "unknown"
        dirty = run("status", "--porcelain", "--untracked-files=no").stdout.strip()
        return head.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
