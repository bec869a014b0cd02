"""Observation encoders: flatten vectors; CNNs for images (paper appendix "CNN"); agent-centred maps turned to the
agent's heading; a three-layer MLP on the flattened observation (the original release's deeper embedding).

Images arrive as `(H, W, C)`; uint8 images are scaled to [0, 1]. `FullImageCNN` is for images larger than
20 pixels, `SmallImageCNN` for smaller ones (e.g. the (2, 3, 2) maze view).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ..memory import MLP, Dense, flat_draw


def _to_unit(x: Array) -> Float[Array, "h w c"]:
    if jnp.issubdtype(x.dtype, jnp.integer):
        return x.astype(jnp.float32) / 255.0
    return x.astype(jnp.float32)


class Flatten(eqx.Module):
    """Observations flattened, as float32 (integer images scaled to [0, 1] like the CNNs' inputs)."""

    out_size: int = eqx.field(static=True)

    def __call__(self, x: Array) -> Float[Array, " out"]:
        x = _to_unit(x) if x.ndim == 3 else x.astype(jnp.float32)
        return jnp.reshape(x, (-1,))


class MLPEncoder(eqx.Module):
    """The flattened observation through `Dense(in, h) → ReLU → Dense(h, h) → ReLU → Dense(h, h) → ReLU`.

    Before a GRU (whose own `Dense → ReLU` follows) it makes the four-layer embedding of the original release's
    recurrent agent (PyPI `pobax==0.0.1`: its saved parameters hold `embedding/Dense_0..3`, `in → h` then three
    `h → h`, ahead of the GRU, for T-Maze, RockSample and Battleship alike), where the paper's listing has one
    `Dense → ReLU` (`docs/parity.md`, "The original's recurrent agent")."""

    flatten: Flatten
    mlp: MLP
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray):
        self.flatten = Flatten(in_size)
        self.mlp = MLP((in_size, hidden_size, hidden_size, hidden_size), key=key)
        self.out_size = hidden_size

    def __call__(self, x: Array) -> Float[Array, " h"]:
        return jax.nn.relu(self.mlp(self.flatten(x)))  # `MLP` has no ReLU after its last layer


def conv2d(in_channels: int, out_channels: int, kernel: int, stride: int = 1, *, key: PRNGKeyArray) -> eqx.nn.Conv2d:
    """`eqx.nn.Conv2d(..., padding="SAME", key=key)` with the same weights and bias (Equinox's initialisation:
    uniform within ±1/√fan-in, weight and bias from the key split in two; tested equal), drawn flat
    (`pobax.memory.flat_draw`, which halves the compile of a map encoder's initialisation on a CPU)."""
    shaped = eqx.filter_eval_shape(
        lambda: eqx.nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding="SAME", key=jax.random.key(0)))
    k_weight, k_bias = jax.random.split(key, 2)
    lim = 1.0 / math.sqrt(in_channels * kernel * kernel)
    draw = lambda k, x: flat_draw(jax.random.uniform, k, x.shape, dtype=x.dtype, minval=-lim, maxval=lim)  # noqa: E731
    return eqx.tree_at(lambda c: (c.weight, c.bias), shaped,
                       (draw(k_weight, shaped.weight), draw(k_bias, shaped.bias)))


class _ConvStack(eqx.Module):
    convs: tuple[eqx.nn.Conv2d, ...]

    def __call__(self, x: Float[Array, "c h w"]) -> Float[Array, "c2 h2 w2"]:
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < len(self.convs) - 1:
                x = jax.nn.relu(x)
        return x


def _out_size(stack: "_ConvStack", shape: tuple[int, int, int]) -> int:
    """Number of features after the convolutions, for an (H, W, C) input (asks JAX, so padding rules are exact)."""
    h, w, c = shape
    out = jax.eval_shape(stack, jax.ShapeDtypeStruct((c, h, w), jnp.float32))
    return out.shape[0] * out.shape[1] * out.shape[2]


class FullImageCNN(eqx.Module):
    """Conv(7×7, /4) → ReLU → Conv(5×5, /2) → ReLU → Conv(3×3, /2) → ReLU → Conv(3×3, /2) → Flatten → ReLU →
    Dense(h) → ReLU → Dense(h). Convolutions use SAME padding so that 32-px frames stay non-empty."""

    stack: _ConvStack
    dense1: Dense
    dense2: Dense
    out_size: int = eqx.field(static=True)

    def __init__(self, shape: tuple[int, int, int], hidden_size: int, *, key: PRNGKeyArray, channels: int = 32):
        h, w, c = shape
        ks = jax.random.split(key, 6)
        specs = [(c, 7, 4), (channels, 5, 2), (channels, 3, 2), (channels, 3, 2)]
        convs = tuple(conv2d(cin, channels, k, stride=s, key=kk) for (cin, k, s), kk in zip(specs, ks[:4]))
        self.stack = _ConvStack(convs)
        self.dense1 = Dense(_out_size(self.stack, shape), hidden_size, key=ks[4])
        self.dense2 = Dense(hidden_size, hidden_size, key=ks[5])
        self.out_size = hidden_size

    def __call__(self, x: Array) -> Float[Array, " out"]:
        y = self.stack(jnp.transpose(_to_unit(x), (2, 0, 1)))
        y = jax.nn.relu(jnp.reshape(y, (-1,)))
        return self.dense2(jax.nn.relu(self.dense1(y)))


class SmallImageCNN(eqx.Module):
    """Three convolutions (kernel `kernel`, stride 1, SAME padding) with ReLU, Flatten, Dense(h)."""

    stack: _ConvStack
    dense: Dense
    out_size: int = eqx.field(static=True)

    def __init__(
        self, shape: tuple[int, int, int], hidden_size: int, *, key: PRNGKeyArray, channels: int = 32, kernel: int = 2
    ):
        h, w, c = shape
        ks = jax.random.split(key, 4)
        convs = tuple(conv2d(cin, channels, kernel, key=kk) for cin, kk in zip((c, channels, channels), ks[:3]))
        self.stack = _ConvStack(convs)
        self.dense = Dense(_out_size(self.stack, shape), hidden_size, key=ks[3])
        self.out_size = hidden_size

    def __call__(self, x: Array) -> Float[Array, " out"]:
        y = jax.nn.relu(self.stack(jnp.transpose(_to_unit(x), (2, 0, 1))))
        return self.dense(jnp.reshape(y, (-1,)))


class Egocentric(eqx.Module):
    """A top-down map centred on the agent, turned to face where the agent faces, flattened.

    For observations like the DMLab mazes' `full` view: an (H, W, C) map with the agent at the centre cell (H and W
    odd) whose last four channels are the agent's heading, one-hot and the same in every cell, in MiniGrid's
    convention (0 east, 1 south, 2 west, 3 north). The other C - 4 channels are padded with zeros to a square and
    rotated so that the heading points up (towards row 0): the cells ahead of the agent are then always the same
    inputs, as in a first-person view, and the heading channels are dropped. The map's information is unchanged."""

    pad: tuple[int, int] = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, shape: tuple[int, int, int]):
        h, w, c = shape
        if h % 2 == 0 or w % 2 == 0 or c < 5:
            raise ValueError(f"encoder 'egocentric' needs an agent-centred map (H, W odd) with its heading in the last "
                             f"4 of at least 5 channels, got shape {shape}: use flatten.")
        side = max(h, w)
        self.pad = ((side - h) // 2, (side - w) // 2)
        self.out_size = side * side * (c - 4)

    def __call__(self, x: Array) -> Float[Array, " out"]:
        x = _to_unit(x)
        heading = jnp.argmax(x[0, 0, -4:])
        (ph, pw) = self.pad
        grid = jnp.pad(x[..., :-4], ((ph, ph), (pw, pw), (0, 0)))
        # Heading d is turned to north (3) by (d + 1) % 4 quarter turns counter-clockwise.
        turns = [lambda g, k=k: jnp.rot90(g, k, axes=(0, 1)) for k in range(4)]
        return jnp.reshape(jax.lax.switch((heading + 1) % 4, turns, grid), (-1,))


def encoder_kind(shape: tuple[int, ...], kind: str = "auto") -> str:
    """The encoder `kind` names for observations of `shape`: "auto" resolved by the paper's rule (Flatten for
    vectors, SmallImageCNN for images of at most 20 px a side, FullImageCNN above), any other kind as given."""
    if kind != "auto":
        return kind
    return "flatten" if len(shape) != 3 else ("full_cnn" if max(shape[0], shape[1]) > 20 else "small_cnn")


def make_encoder(shape: tuple[int, ...], hidden_size: int, *, key: PRNGKeyArray, kind: str = "auto") -> eqx.Module:
    """The encoder for observations of `shape`. kind "auto": Flatten for vectors; SmallImageCNN for images of
    at most 20 px a side, FullImageCNN above (the paper's rule). "flatten", "small_cnn" (at most 20 px),
    "full_cnn" force one; "egocentric" turns an agent-centred map with heading channels to the agent's heading
    (`Egocentric`); "mlp" puts three `Dense → ReLU` layers on the flattened observation (`MLPEncoder`)."""
    kind = encoder_kind(shape, kind)
    if kind in ("small_cnn", "full_cnn") and len(shape) != 3:
        raise ValueError(f"encoder {kind!r} needs image observations (H, W, C), got shape {shape}: use flatten.")
    if kind == "small_cnn" and max(shape[0], shape[1]) > 20:
        # Stride 1 keeps every pixel through three convolutions: a 37x61 maze map at the paper's 512 environments
        # asked for 118 GB on a GPU. The paper's rule gives such images the strided FullImageCNN.
        raise ValueError(f"encoder 'small_cnn' is for images of at most 20 px a side (stride 1 keeps every pixel), got "
                         f"{shape[0]}x{shape[1]}: use full_cnn (the paper's rule for larger images) or flatten.")
    if kind == "full_cnn":
        return FullImageCNN(shape, hidden_size, key=key)
    if kind == "small_cnn":
        return SmallImageCNN(shape, hidden_size, key=key)
    if kind == "egocentric":
        if len(shape) != 3:
            raise ValueError(f"encoder 'egocentric' needs a map observation (H, W, C), got shape {shape}: use flatten.")
        return Egocentric(shape)
    if kind not in ("flatten", "mlp"):
        raise ValueError(f"Unknown encoder {kind!r}: choose auto, flatten, small_cnn, full_cnn, egocentric or mlp.")
    size = 1
    for s in shape:
        size *= s
    return Flatten(size) if kind == "flatten" else MLPEncoder(size, hidden_size, key=key)
