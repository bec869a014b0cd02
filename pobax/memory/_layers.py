"""Small layers shared by memories and agent heads: orthogonal-initialised dense layers and MLPs."""

import contextlib
import contextvars
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray


def expand_to(b: Array, ndim: int) -> Array:
    """A bias of shape (n,) as (1, ..., 1, n) with `ndim` axes: explicit broadcasting (rank promotion is an
    error in the tests, to catch (N, 1) − (N,) bugs)."""
    return jnp.reshape(b, (1,) * (ndim - 1) + b.shape)


#: How `orthogonal` orthonormalises: "auto" (QR decomposition on a GPU, Gram–Schmidt elsewhere), "qr" or
#: "gram_schmidt".
ORTHOGONAL_METHOD = "auto"


def orthogonal(key: PRNGKeyArray, shape: tuple[int, int], scale: float = 1.0) -> Float[Array, "rows cols"]:
    """A random (semi-)orthogonal matrix of `shape` times `scale`: rows or columns orthonormal, whichever fit.

    The Q factor, with a positive diagonal of R, of the QR decomposition of a Gaussian matrix — a Haar-distributed
    orthogonal matrix, like `jax.nn.initializers.orthogonal`. Q is unique, so the two ways of computing it agree
    to rounding (tested): on a GPU, the QR decomposition (one cuSOLVER call; a Gram–Schmidt loop per weight
    matrix added 0.7 s to the compile time of a training run); elsewhere Gram–Schmidt with re-orthogonalisation in
    plain JAX operations, because jaxlib's CPU LAPACK QR kernel can deadlock when several batched QRs (model
    initialisation vmapped over seeds) run at once on a small machine.
    """
    rows, cols = shape
    m, k = max(rows, cols), min(rows, cols)
    a = jax.random.normal(key, (m, k), jnp.float32)
    method = ORTHOGONAL_METHOD
    if method == "auto":
        method = "qr" if jax.default_backend() == "gpu" else "gram_schmidt"
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


#: `x @ W.T` is computed as a broadcast multiply and a sum, which XLA fuses with its neighbours, instead of a GEMM
#: (for which XLA's GPU autotuner compiles and times ~10 Triton tilings per distinct shape) when the input has one
#: row and, counting the rows that the `vmap`s around the call add (declared with `matmul_batch`), rows × weight
#: entries ≤ `REDUCE_MAX_WORK`: the multiply-sum reads the weight once per row. That is the rollout of a small
#: batch: the network on one time step of one environment, vmapped over environments and runs. None (default):
#: 2**22 on accelerators, 0 (always a GEMM) on the CPU, where the GEMM is faster. Same function (float rounding
#: aside; tested). Measured on an H200 (benchmarks/README.md, "Session 8"): T-Maze GRU 1 seed trains 20% faster,
#: × 30 seeds and RockSample GRU 1 seed 3-4%; with no bound, RockSample × 10 seeds ran 2% slower and Battleship
#: (hidden 512, 32 environments) 5% slower. A sharded run declares all its runs (an upper bound per device).
REDUCE_MAX_WORK: int | None = None
_BATCH = contextvars.ContextVar("pobax_matmul_batch", default=0)


@contextlib.contextmanager
def matmul_batch(rows: int):
    """Within: `matmul_t` takes its input to be repeated `rows` times by the `vmap`s around it (at most)."""
    token = _BATCH.set(rows)
    try:
        yield
    finally:
        _BATCH.reset(token)


_SPLIT = contextvars.ContextVar("pobax_split_gemms", default=False)


@contextlib.contextmanager
def split_gemms(on: bool = True):
    """Within (while tracing, on an NVIDIA GPU), with `on`: the products over whole sequences (an input of more than
    one row: the replay's dense layers, the GRU's input projection and weight gradient) are isolated behind
    `jax.lax.optimization_barrier`s, forward and backward, so that XLA's GEMM fusion finds nothing to fuse into them
    and, with `xla_gpu_triton_gemm_any` off, leaves them to cuBLAS; the products inside sequential loops (the
    rollout's steps, the GRU's recurrence) are given the TF32 dot algorithm (what DEFAULT precision does there),
    which XLA's GEMM fusion always gives to Triton. Same functions (float rounding aside). `pobax.agent.train` turns
    it on for wide networks (`pobax.agent._train.CUBLAS_MIN_HIDDEN`)."""
    token = _SPLIT.set(on)
    try:
        yield
    finally:
        _SPLIT.reset(token)


# The network's products spell out their precision (DEFAULT, what `a @ b` has; or the TF32 algorithm, see
# `split_gemms`): `pobax.agent._train` tells them from any other product of a program (physics, attention) by it.
_DEFAULT = jax.lax.Precision.DEFAULT


def sequence_matmul(a: Array, b: Array) -> Array:
    """`a @ b` over whole sequences (see `split_gemms`)."""
    if not _SPLIT.get():
        return jnp.matmul(a, b, precision=_DEFAULT)
    a, b = jax.lax.optimization_barrier((a, b))
    return jax.lax.optimization_barrier(jnp.matmul(a, b, precision=_DEFAULT))


def loop_matmul(a: Array, b: Array) -> Array:
    """`a @ b` inside a sequential loop (see `split_gemms`)."""
    return jnp.matmul(a, b, precision=jax.lax.DotAlgorithmPreset.TF32_TF32_F32 if _SPLIT.get() else _DEFAULT)


def matmul_t(x: Float[Array, "*batch in"], w: Float[Array, "out in"]) -> Float[Array, "*batch out"]:
    """`x @ w.T`, as a broadcast multiply and sum where `REDUCE_MAX_WORK` says so."""
    limit = REDUCE_MAX_WORK
    if limit is None:
        limit = 0 if jax.default_backend() == "cpu" else 2**22
    rows = math.prod(x.shape[:-1])
    if rows == 1 and 0 < _BATCH.get() * w.size <= limit:
        return jnp.sum(x[..., None, :] * jnp.reshape(w, (1,) * (x.ndim - 1) + w.shape), axis=-1)
    if rows > 1:
        return sequence_matmul(x, w.T)
    return loop_matmul(x, w.T)


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
