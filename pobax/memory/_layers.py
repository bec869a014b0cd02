"""Small layers shared by memories and agent heads: orthogonal-initialised dense layers and MLPs."""

import contextlib
import contextvars
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._backend import orthogonal_method, rollout_reduce_limit


def expand_to(b: Array, ndim: int) -> Array:
    """A bias of shape (n,) as (1, ..., 1, n) with `ndim` axes: explicit broadcasting (rank promotion is an
    error in the tests, to catch (N, 1) − (N,) bugs)."""
    return jnp.reshape(b, (1,) * (ndim - 1) + b.shape)


def orthogonal(key: PRNGKeyArray, shape: tuple[int, int], scale: float = 1.0, *,
               method: str = "auto") -> Float[Array, "rows cols"]:
    """A random (semi-)orthogonal matrix of `shape` times `scale`: rows or columns orthonormal, whichever fit.

    The Q factor, with a positive diagonal of R, of the QR decomposition of a Gaussian matrix — a Haar-distributed
    orthogonal matrix, like `jax.nn.initializers.orthogonal`. Q is unique, so the two ways of computing it agree to
    rounding (tested): `method` "qr" (a QR decomposition) or "gram_schmidt" (with re-orthogonalisation, in plain JAX
    operations); "auto" is the backend's choice (`pobax._backend.orthogonal_method`).
    """
    rows, cols = shape
    m, k = max(rows, cols), min(rows, cols)
    a = jax.random.normal(key, (m, k), jnp.float32)
    if method == "auto":
        method = orthogonal_method()
    q = _q_by_qr(a) if method == "qr" else _q_by_gram_schmidt(a)
    return scale * (q if rows >= cols else q.T)


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


# The rows that the `vmap`s around a dense layer add, and the work bound below which one step is a multiply-sum
# (`matmul_batch`): a context that the training loop sets from its configuration while it traces the rollout.
_BATCH = contextvars.ContextVar("pobax_matmul_batch", default=(0, 0))


@contextlib.contextmanager
def matmul_batch(rows: int, limit: int | None = None):
    """Within: `matmul_t` takes its one-row inputs to be repeated `rows` times by the `vmap`s around it (the rollout:
    one time step of every environment of every run), and computes `x @ w.T` as a broadcast multiply and sum where
    rows × weight entries ≤ `limit` (default: the backend's, `pobax._backend.rollout_reduce_limit`): the
    multiply-sum reads the weight once per row and fuses with its neighbours, which beats a GEMM kernel for small
    batches on accelerators. The same function either way (float rounding aside; tested)."""
    token = _BATCH.set((rows, rollout_reduce_limit() if limit is None else limit))
    try:
        yield
    finally:
        _BATCH.reset(token)


def matmul_t(x: Float[Array, "*batch in"], w: Float[Array, "out in"]) -> Float[Array, "*batch out"]:
    """`x @ w.T`, as a broadcast multiply and sum within `matmul_batch` where its bound says so."""
    rows, limit = _BATCH.get()
    if math.prod(x.shape[:-1]) == 1 and 0 < rows * w.size <= limit:
        return jnp.sum(x[..., None, :] * jnp.reshape(w, (1,) * (x.ndim - 1) + w.shape), axis=-1)
    return x @ w.T


def recurrent_matvec(product: str, weight: Float[Array, "out in"], v: Float[Array, " in"]) -> Float[Array, " out"]:
    """`weight @ v` in a recurrent cell's time loop: a matrix product ("dot") or a broadcast multiply and sum
    ("reduce", which XLA fuses with the gate arithmetic; `pobax._backend.recurrent_product` picks)."""
    return jnp.sum(weight * v[None, :], axis=1) if product == "reduce" else weight @ v


class Dense(eqx.Module):
    """`y = W x + b`, W orthogonal with gain `scale`, b zero (the usual PPO initialisation)."""

    weight: Float[Array, "out in"]
    bias: Float[Array, " out"]

    def __init__(self, in_size: int, out_size: int, *, key: PRNGKeyArray, scale: float = math.sqrt(2.0)):
        self.weight = orthogonal(key, (out_size, in_size), scale)
        self.bias = jnp.zeros((out_size,), jnp.float32)

    def __call__(self, x: Float[Array, "*batch in"]) -> Float[Array, "*batch out"]:
        return matmul_t(x, self.weight) + expand_to(self.bias, x.ndim)


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
