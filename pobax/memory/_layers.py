"""Small layers shared by memories and agent heads: orthogonal-initialised dense layers and MLPs."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._backend import by_lowering_platform, orthogonal_method
from .._modules import map_modules, replace_static


def expand_to(b: Array, ndim: int) -> Array:
    """A bias of shape (n,) as (1, ..., 1, n) with `ndim` axes: explicit broadcasting (rank promotion is an
    error in the tests, to catch (N, 1) − (N,) bugs)."""
    return jnp.reshape(b, (1,) * (ndim - 1) + b.shape)


def flat_draw(sample, key: PRNGKeyArray, shape: tuple[int, ...], **kwargs) -> Array:
    """`sample(key, shape, **kwargs)` (a `jax.random` sampler: `uniform`, `normal`) drawn as one flat vector and
    reshaped: the same values (threefry counts its counters in row-major order; tested), while XLA's optimising CPU
    compiler spends seconds on a draw over three or more axes, which a 2-axis draw becomes when vmapped over runs
    (docs/performance.md, "Compile time"; `python benchmarks/bench_compile.py`)."""
    return jnp.reshape(sample(key, (math.prod(shape),), **kwargs), shape)


def orthogonal(key: PRNGKeyArray, shape: tuple[int, int], scale: float = 1.0, *,
               method: str = "auto") -> Float[Array, "rows cols"]:
    """A random (semi-)orthogonal matrix of `shape` times `scale`: rows or columns orthonormal, whichever fit.

    The Q factor, with a positive diagonal of R, of the QR decomposition of a Gaussian matrix — a Haar-distributed
    orthogonal matrix, like `jax.nn.initializers.orthogonal`. Q is unique, so the two ways of computing it agree to
    rounding (tested): `method` "qr" (a QR decomposition) or "gram_schmidt" (with re-orthogonalisation, in plain JAX
    operations); "auto" (the default) is the choice of the platform the program is compiled for
    (`pobax._backend.orthogonal_method`, chosen when the program is lowered: memories built without configuration,
    a user's included, get it).
    """
    rows, cols = shape
    m, k = max(rows, cols), min(rows, cols)
    a = flat_draw(jax.random.normal, key, (m, k), dtype=jnp.float32)
    if method == "auto":
        q = by_lowering_platform(orthogonal_method, _q, a)
    else:
        q = _q(method, a)
    return scale * (q if rows >= cols else q.T)


def _q(method: str, a: Float[Array, "m k"]) -> Float[Array, "m k"]:
    if method not in ("qr", "gram_schmidt"):
        raise ValueError(f"orthogonal: method must be 'auto', 'qr' or 'gram_schmidt', not {method!r}")
    return _q_by_qr(a) if method == "qr" else _q_by_gram_schmidt(a)


def _q_by_qr(a: Float[Array, "m k"]) -> Float[Array, "m k"]:
    q, r = jnp.linalg.qr(a)
    return q * jnp.where(jnp.diagonal(r) < 0, -1.0, 1.0)[None, :]


def _q_by_gram_schmidt(a: Float[Array, "m k"]) -> Float[Array, "m k"]:
    k = a.shape[1]

    def body(j, q):
        earlier = (jnp.arange(k) < j).astype(q.dtype)
        v = q[:, j]
        for _ in range(2):  # a second pass restores orthogonality lost to rounding ("twice is enough")
            v = v - q @ ((q.T @ v) * earlier)
        return q.at[:, j].set(v / jnp.sqrt(jnp.sum(v * v)))

    return jax.lax.fori_loop(0, k, body, a)


#: `(rows, limit)`: the rows that the `vmap`s around a layer add to its one-row inputs (the rollout: one time step of
#: every environment of every run), and the bound of rows × weight entries up to which `matmul_t` computes such a
#: product as a multiply-sum. `(0, 0)`: no such batch (always a matrix product).
NO_BATCH = (0, 0)


def matmul_t(x: Float[Array, "*batch in"], w: Float[Array, "out in"],
             batch: tuple[int, int] = NO_BATCH) -> Float[Array, "*batch out"]:
    """`x @ w.T`; for a one-row `x` under `vmap`s that make it `rows` rows (`batch = (rows, limit)`), as a broadcast
    multiply and sum where rows × weight entries ≤ `limit`: the multiply-sum reads the weight once per row and fuses
    with its neighbours, which beats a GEMM kernel for small batches on accelerators. The same function either way
    (float rounding aside; tested)."""
    rows, limit = batch
    if math.prod(x.shape[:-1]) == 1 and 0 < rows * w.size <= limit:
        return jnp.sum(x[..., None, :] * jnp.reshape(w, (1,) * (x.ndim - 1) + w.shape), axis=-1)
    return x @ w.T


def with_matmul_batch(tree, rows: int, limit: int):
    """`tree` (a network, or any pytree of modules) with every layer's `matmul_batch` field (`Dense`, and the
    memories that call `matmul_t` themselves) set to `(rows, limit)` (see `NO_BATCH`): what the training loop
    passes down to the network its rollout calls, from its number of runs and environments and the backend's bound
    (`pobax._backend.Backend.reduce_limit`). The parameters are the same arrays."""
    def set_batch(m):
        return replace_static(m, matmul_batch=(rows, limit)) if "matmul_batch" in m.__dataclass_fields__ else m

    return map_modules(set_batch, tree)


def recurrent_matvec(product: str, weight: Float[Array, "out in"], v: Float[Array, " in"]) -> Float[Array, " out"]:
    """`weight @ v` in a recurrent cell's time loop: a matrix product ("dot") or a broadcast multiply and sum
    ("reduce", which XLA fuses with the gate arithmetic; `pobax._backend.recurrent_product` picks)."""
    return jnp.sum(weight * v[None, :], axis=1) if product == "reduce" else weight @ v


class Dense(eqx.Module):
    """`y = W x + b`, W orthogonal with gain `scale`, b zero (the usual PPO initialisation)."""

    weight: Float[Array, "out in"]
    bias: Float[Array, " out"]
    matmul_batch: tuple[int, int] = eqx.field(static=True)  # `matmul_t`'s batch (`with_matmul_batch`)

    def __init__(self, in_size: int, out_size: int, *, key: PRNGKeyArray, scale: float = math.sqrt(2.0)):
        self.weight = orthogonal(key, (out_size, in_size), scale)
        self.bias = jnp.zeros((out_size,), jnp.float32)
        self.matmul_batch = NO_BATCH

    def __call__(self, x: Float[Array, "*batch in"]) -> Float[Array, "*batch out"]:
        return matmul_t(x, self.weight, self.matmul_batch) + expand_to(self.bias, x.ndim)


class MLP(eqx.Module):
    """Dense layers with ReLU between them (none after the last)."""

    layers: tuple[Dense, ...]

    def __init__(self, sizes: tuple[int, ...], *, key: PRNGKeyArray, final_scale: float = math.sqrt(2.0)):
        keys = jax.random.split(key, len(sizes) - 1)
        n = len(sizes) - 1
        self.layers = tuple(
            Dense(sizes[i], sizes[i + 1], key=keys[i], scale=final_scale if i == n - 1 else math.sqrt(2.0))
            for i in range(n)
        )

    def __call__(self, x: Float[Array, "*batch in"]) -> Float[Array, "*batch out"]:
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = jax.nn.relu(x)
        return x
