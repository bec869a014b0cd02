import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The suite is compile-bound: XLA's CPU backend without LLVM's expensive optimisations compiles about a third
# faster, for slower steps that tests do not notice (as `TrainConfig.fast_compile`). Subprocesses inherit it.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
                               " --xla_llvm_disable_expensive_passes=true").strip()

# The same small programs compile again and again (the hostile tests' runs, CLI commands in subprocesses, several
# test modules' tiny configurations): one JAX compilation cache for the run loads them instead. Made by the first
# process (xdist's controller), inherited by its workers and their subprocesses, removed at the end of the run
# (`pytest_sessionfinish`). A cache configured outside is kept, and left in place.
_TEST_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ and "POBAX_COMPILE_CACHE" not in os.environ:
    import tempfile

    _TEST_CACHE = os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="pobax-tests-xla-")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"

import jax  # noqa: E402

# Catch (N, 1) - (N,) broadcasting bugs in pobax's own code. Third-party code that breaks under it is scoped
# with `jax.numpy_rank_promotion("allow")` where it is called.
jax.config.update("jax_numpy_rank_promotion", "raise")


import gc  # noqa: E402

import pytest  # noqa: E402


def pytest_sessionfinish(session, exitstatus):
    if _TEST_CACHE is not None:  # (the process that made it: workers inherited it, _TEST_CACHE None there)
        import shutil

        shutil.rmtree(_TEST_CACHE, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module: one process runs the whole suite, and Brax, Craftax
    and the pixel renderer leave large executables behind (a full run once crashed inside XLA's compiler late in
    the suite)."""
    yield
    jax.clear_caches()
    gc.collect()


# --- the hostile-user tests' runs and cells (test_hostile.py, test_hostile_inputs.py) ------------------------------

@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A tiny T-Maze 5 run (`_hostile.CFG`) stopped after 3 of its 8 chunks (resumable)."""
    from _hostile import CFG, train

    run = tmp_path_factory.mktemp("hostile") / "stopped"
    train(CFG, run, progress=False, max_chunks=3)
    return run


@pytest.fixture(scope="module")
def finished(tmp_path_factory, stopped):
    """`stopped`, resumed to its end."""
    from _hostile import CFG, copy, train

    run = copy(stopped, tmp_path_factory.mktemp("hostile") / "finished")
    train(CFG, run, progress=False, resume=True)
    return run


@pytest.fixture
def user_cells(tmp_path, monkeypatch):
    """User memory cells that misbehave (cells.py: outputs wider than declared, a bug inside, NaN outputs) and a
    module that exits on import (quitter.py), importable from `tmp_path`."""
    import textwrap

    (tmp_path / "cells.py").write_text(textwrap.dedent("""
        import equinox as eqx, jax.numpy as jnp
        from pobax.memory import AbstractMemory, Dense

        class Wide(AbstractMemory):
            proj: Dense
            in_size: int = eqx.field(static=True)
            out_size: int = eqx.field(static=True)

            def __init__(self, in_size, hidden_size, *, key):
                self.in_size, self.out_size = in_size, hidden_size
                self.proj = Dense(in_size, hidden_size + 3, key=key)  # three more outputs than it declares

            def init_carry(self):
                return jnp.zeros(self.out_size)

            def __call__(self, carry, xs, starts):
                return carry, jnp.tanh(self.proj(xs))

        class Buggy(Wide):
            def __call__(self, carry, xs, starts):
                raise ValueError("a bug inside the cell")

        class NaN(Wide):  # the shapes it declares, and NaN outputs: every run diverges
            def __call__(self, carry, xs, starts):
                return carry, self.proj(xs)[:, : self.out_size] * jnp.nan

        class Triple(Wide):  # (carry, ys, ys): one value too many
            def __call__(self, carry, xs, starts):
                ys = jnp.tanh(self.proj(xs)[:, : self.out_size])
                return carry, ys, ys

        class IntOut(Wide):  # the declared shape, integer outputs: no gradient would reach the memory
            def __call__(self, carry, xs, starts):
                return carry, (self.proj(xs)[:, : self.out_size] > 0).astype(jnp.int32)

        class CarryGrows(Wide):  # a carry one longer than init_carry()'s after every call
            def __call__(self, carry, xs, starts):
                return jnp.concatenate([carry, carry[:1]]), jnp.tanh(self.proj(xs)[:, : self.out_size])

        class NonStatic(AbstractMemory):  # its sizes are fields, not static: leaves pobax would vmap over
            proj: Dense
            in_size: int
            out_size: int

            def __init__(self, in_size, hidden_size, *, key):
                self.in_size, self.out_size = in_size, hidden_size
                self.proj = Dense(in_size, hidden_size, key=key)

            def init_carry(self):
                return jnp.zeros(self.out_size)

            def __call__(self, carry, xs, starts):
                return carry, jnp.tanh(self.proj(xs))
    """))
    (tmp_path / "quitter.py").write_text("import sys\nsys.exit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path
