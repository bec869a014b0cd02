"""JAX's persistent compilation cache for pobax programs.

A training program compiles in 10-70 s on a GPU. With the persistent cache on, a later process that compiles the
same program (same structural configuration, number of runs and device: a repeated experiment, a continued gap
report, `--resume`) loads the executable from disk instead.
"""

import os
from pathlib import Path

import jax

from .._backend import platform_of
from .._paths import cache_dir

#: Environment variable: a directory for the cache, or "off".
ENV_VAR = "POBAX_COMPILE_CACHE"


def enable_compile_cache(path: str | os.PathLike | None = None, *, accelerators_only: bool = False,
                         devices=None) -> Path | None:
    """Turn on JAX's persistent compilation cache in `path` (default: $POBAX_COMPILE_CACHE, else
    `cache_dir()/xla`, i.e. ~/.cache/pobax/xla) and return the directory; None when it stays off. A `path` given
    wins over the variable. Without one it stays off when $POBAX_COMPILE_CACHE is "off"; it stays off too when a cache
    directory is already configured (that one is kept), or, with `accelerators_only`, when `devices` (default: JAX's
    default devices) are CPUs (the CLI's default: CPU programs compile in seconds)."""
    setting = os.environ.get(ENV_VAR)
    if path is None and setting == "off":
        return None
    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    if path is None and setting is None and accelerators_only and platform_of(devices) == "cpu":
        return None
    cache = Path(path if path is not None else (setting or cache_dir() / "xla")).expanduser()
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # an unwritable cache directory must not stop training
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return cache
