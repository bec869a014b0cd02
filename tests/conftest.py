import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The suite is compile-bound: XLA's CPU backend without LLVM's expensive optimisations compiles about a third
# faster, for slower steps that tests do not notice (as `TrainConfig.fast_compile`). Subprocesses inherit it.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
                               " --xla_llvm_disable_expensive_passes=true").strip()

import jax  # noqa: E402

# Catch (N, 1) - (N,) broadcasting bugs in pobax's own code. Third-party code that breaks under it is scoped
# with `jax.numpy_rank_promotion("allow")` where it is called.
jax.config.update("jax_numpy_rank_promotion", "raise")


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module: one process runs the whole suite, and Brax, Craftax
    and the pixel renderer leave large executables behind (a full run once crashed inside XLA's compiler late in
    the suite)."""
    yield
    jax.clear_caches()
    gc.collect()
