"""Where pobax keeps derived files (Craftax textures, compiled programs)."""

import os
from pathlib import Path


def cache_dir() -> Path:
    """`$POBAX_CACHE_DIR`, else `$XDG_CACHE_HOME/pobax`, else `~/.cache/pobax`."""
    if os.environ.get("POBAX_CACHE_DIR"):
        return Path(os.environ["POBAX_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pobax"
