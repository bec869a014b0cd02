"""The package's version, and the commit of the code that produced a result (provenance of run directories).

The commit is what the package reads itself, never a value passed in from outside:
- in a git checkout (an editable install, `python cli.py` from the tree): `git rev-parse HEAD`, with `-dirty` when
  tracked files differ from it;
- in a tree made by `git archive` (how a fixed commit travels to a machine without the repository): the commit
  `git archive` wrote into `_commit.txt` (`.gitattributes`: export-subst), with `-archive` appended;
- otherwise (an installed copy without git): `version-<package version>`.
"""

import functools
import importlib.metadata
import os
import subprocess
from pathlib import Path

try:
    __version__ = importlib.metadata.version("pobax-bench")
except importlib.metadata.PackageNotFoundError:  # imported from a checkout that was not installed
    __version__ = "0+unknown"

_STAMP = Path(__file__).resolve().parent / "_commit.txt"


def _git(root: Path, *args: str) -> subprocess.CompletedProcess:
    """git on the package's own checkout: without the caller's GIT_* variables, through which `GIT_DIR` (set, for
    one, inside git hooks) would name another repository's commit."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, env=env)


@functools.cache
def commit() -> str:
    """The commit of this code (see the module docstring): a 12-character hash with `-dirty` (a checkout with
    changes) or `-archive` (a tree from `git archive`), else `version-<version>`."""
    root = Path(__file__).resolve().parent.parent
    if (root / ".git").exists():
        try:
            head = _git(root, "rev-parse", "--short=12", "HEAD")
            if head.returncode == 0:
                dirty = _git(root, "status", "--porcelain", "--untracked-files=no").stdout.strip()
                return head.stdout.strip() + ("-dirty" if dirty else "")
        except (OSError, subprocess.SubprocessError):
            pass
    try:
        stamp = _STAMP.read_text().strip()
    except OSError:
        stamp = ""
    if stamp and not stamp.startswith("$Format"):  # substituted by `git archive`
        return stamp[:12] + "-archive"
    return f"version-{__version__}"
