import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

# Catch (N, 1) - (N,) broadcasting bugs in pobax's own code. Third-party code that breaks under it is scoped
# with `jax.numpy_rank_promotion("allow")` where it is called.
jax.config.update("jax_numpy_rank_promotion", "raise")
