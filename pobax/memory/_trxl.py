"""Gated Transformer-XL memory (GTrXL, Parisotto et al. 2020) with relative positions and an episode-aware cache.

`Dense(in, embed) → num_layers × [relative multi-head attention → gate → position-wise feed-forward → gate]`.
Each block is pre-LayerNorm ("identity map reordering") and its residual connections are GRU-type gates whose
z-bias starts at `−gating_bias`, so each block starts close to the identity map.

The carry caches, for every layer, that layer's *inputs* at the last `window_mem` steps, and which of those
steps belong to the current episode. A query at step `t` attends to itself and to the `window_mem` steps before
it, provided they are in the same episode: attention never crosses an episode start. Because that context is a
sliding window of fixed length (not "the whole cache plus the window so far"), the result does not depend on
how the sequence is chunked: stepping one at a time (rollout) gives the same outputs as one call over the
whole sequence from the same carry (replay), up to float rounding.

A long sequence is processed `window_grad` steps at a time (a `lax.scan` over windows), each window attending
to [cache; window] under the mask above; the cache is updated after each window with `stop_gradient`, so
gradients flow only within a window (truncated backpropagation, as in Transformer-XL).

Rollout steps are cheap without caching projected keys and values: attention is computed with the key,
value and position projections absorbed into the query and the output (`_Block._attend_absorbed`), so a step
only layer-normalises the cached inputs. Caching projected keys/values instead would tie them to the
parameters of the rollout that made them: after a PPO update the next rollout would attend with stale keys
while the replay (and the textbook computation) recomputes them, so rollout and replay would disagree.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ._base import AbstractMemory, check_inputs
from ._layers import Dense


class TrXLCarry(eqx.Module):
    """What a Transformer-XL remembers between calls."""

    memory: Float[Array, "num_layers window_mem embed"]  # inputs of each layer at the last window_mem steps
    valid: Bool[Array, " window_mem"]  # the cached step belongs to the current episode (oldest first)


def _sinusoid(distances: Int[Array, " n"], size: int) -> Float[Array, "n size"]:
    """Transformer-XL's sinusoidal embedding of relative distances."""
    inv_freq = 1.0 / (10000.0 ** (jnp.arange(0, size, 2, dtype=jnp.float32) / size))
    angles = distances.astype(jnp.float32)[:, None] * inv_freq[None, :]
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)[:, :size]


class _Gate(eqx.Module):
    """GTrXL's GRU-type gate `g(x, y)`: x is the residual stream, y the sub-layer's output.

    `r = σ(W_r y + U_r x)`, `z = σ(W_z y + U_z x + b_z)`, `h = tanh(W_g y + U_g (r ⊙ x))`,
    `g = (1 − z) ⊙ x + z ⊙ h`, with `b_z` initialised to `−gating_bias` so that `g ≈ x` at first.
    """

    from_y: Dense  # (W_r, W_z, W_g) stacked
    from_x: Dense  # (U_r, U_z) stacked
    from_rx: Dense  # U_g

    def __init__(self, size: int, gating_bias: float, *, key: PRNGKeyArray):
        ky, kx, kg = jax.random.split(key, 3)
        from_y = Dense(size, 3 * size, key=ky, scale=1.0)
        self.from_y = eqx.tree_at(lambda d: d.bias, from_y, from_y.bias.at[size : 2 * size].set(-gating_bias))
        self.from_x = Dense(size, 2 * size, key=kx, scale=1.0)
        self.from_rx = Dense(size, size, key=kg, scale=1.0)

    def __call__(self, x: Float[Array, "n size"], y: Float[Array, "n size"]) -> Float[Array, "n size"]:
        gy_r, gy_z, gy_h = jnp.split(self.from_y(y), 3, axis=-1)
        gx_r, gx_z = jnp.split(self.from_x(x), 2, axis=-1)
        r = jax.nn.sigmoid(gy_r + gx_r)
        z = jax.nn.sigmoid(gy_z + gx_z)
        h = jnp.tanh(gy_h + self.from_rx(r * x))
        return (1.0 - z) * x + z * h


class _Block(eqx.Module):
    """One GTrXL layer: relative multi-head attention and a feed-forward layer, each pre-normed and gated."""

    norm_attn: eqx.nn.LayerNorm  # one norm for cached and current steps: a key must not depend on where it is
    query: Dense
    key_value: Dense
    pos: Dense  # W_R: projects the sinusoid of a relative distance into key space
    content_bias: Float[Array, "heads head_dim"]  # Transformer-XL's u
    pos_bias: Float[Array, "heads head_dim"]  # Transformer-XL's v
    out: Dense
    norm_ff: eqx.nn.LayerNorm
    ff: tuple[Dense, Dense]
    gate_attn: _Gate | None
    gate_ff: _Gate | None
    num_heads: int = eqx.field(static=True)

    def __init__(self, embed: int, num_heads: int, qkv: int, gating: bool, gating_bias: float, *, key):
        if qkv % num_heads != 0:
            raise ValueError(f"qkv_features ({qkv}) must be a multiple of num_heads ({num_heads})")
        kq, kkv, kp, ko, kf1, kf2, kg1, kg2 = jax.random.split(key, 8)
        self.num_heads = num_heads
        self.norm_attn, self.norm_ff = eqx.nn.LayerNorm(embed), eqx.nn.LayerNorm(embed)
        self.query = Dense(embed, qkv, key=kq, scale=1.0)
        self.key_value = Dense(embed, 2 * qkv, key=kkv, scale=1.0)
        self.pos = Dense(embed, qkv, key=kp, scale=1.0)
        self.content_bias = jnp.zeros((num_heads, qkv // num_heads), jnp.float32)
        self.pos_bias = jnp.zeros((num_heads, qkv // num_heads), jnp.float32)
        self.out = Dense(qkv, embed, key=ko, scale=1.0)
        self.ff = (Dense(embed, embed, key=kf1), Dense(embed, embed, key=kf2, scale=1.0))
        self.gate_attn = _Gate(embed, gating_bias, key=kg1) if gating else None
        self.gate_ff = _Gate(embed, gating_bias, key=kg2) if gating else None

    def absorbs(self, queries: int, keys: int) -> bool:
        """Whether attending with `queries` queries to `keys` keys is cheaper with the projections absorbed.

        Multiply-adds of the two exact ways to compute the same attention (`keys` ≈ window_mem + queries;
        position terms count like keys): projecting keys, values and positions costs ≈ 3·keys·embed·qkv +
        3·queries·keys·qkv; absorbing them ≈ 3·heads·queries·keys·embed + 3·queries·embed·qkv. A single
        step (rollout, evaluation) always absorbs; replay windows absorb when embed is small next to head_dim.
        """
        embed, qkv = self.norm_attn.shape[0], self.query.weight.shape[0]
        absorbed = self.num_heads * queries * keys * embed + queries * embed * qkv
        projected = keys * embed * qkv + queries * keys * qkv
        return absorbed < projected

    def __call__(
        self,
        x: Float[Array, "q embed"],
        mem: Float[Array, "m embed"],
        distance: Int[Array, "q m+q"],
        mask: Bool[Array, "q m+q"],
        rel: Float[Array, "d embed"],
        absorb: bool | None = None,
    ) -> Float[Array, "q embed"]:
        """One block over a window `x` whose queries attend to `[mem; x]` under `mask`.

        `absorb` picks between two computations of the same function (equal up to float rounding):
        `False` projects every key, value and relative position (the textbook form); `True` folds the key
        and position projections into the query and applies the value projection after the attention
        average, so that cached steps are only layer-normalised, never projected (see `_attend_absorbed`).
        `None` picks the cheaper one for these sizes (`absorbs`).
        """
        heads = self.num_heads
        kv_in = jax.vmap(self.norm_attn)(jnp.concatenate([mem, x]))  # keys/values: [cache; window]
        x_norm = kv_in[mem.shape[0] :]  # queries: the window
        q = self.query(x_norm).reshape(x.shape[0], heads, -1)
        if absorb is None:
            absorb = self.absorbs(x.shape[0], kv_in.shape[0])
        attend = self._attend_absorbed if absorb else self._attend_projected
        attended = attend(q, kv_in, distance, mask, rel).reshape(x.shape[0], -1)
        y = jax.nn.relu(self.out(attended))
        x = self.gate_attn(x, y) if self.gate_attn is not None else x + y
        y = jax.nn.relu(self.ff[1](jax.nn.relu(self.ff[0](jax.vmap(self.norm_ff)(x)))))
        return self.gate_ff(x, y) if self.gate_ff is not None else x + y

    def _attend_projected(self, q, kv_in, distance, mask, rel) -> Float[Array, "q heads head_dim"]:
        """Relative attention with every key, value and position projected (Transformer-XL's form)."""
        heads = self.num_heads
        kv = self.key_value(kv_in).reshape(kv_in.shape[0], 2, heads, -1)
        k, v = kv[:, 0], kv[:, 1]
        r = self.pos(rel).reshape(rel.shape[0], heads, -1)
        content = jnp.einsum("qhc,khc->hqk", q + self.content_bias[None], k)
        # Position term for every distance 0..window_mem, then gathered per (query, key) pair: cheaper than
        # embedding every pair, and simpler than Transformer-XL's "relative shift" trick.
        by_distance = jnp.einsum("qhc,dhc->hqd", q + self.pos_bias[None], r)
        weights = self._weights(content, by_distance, distance, mask, q.shape[-1])
        return jnp.einsum("hqk,khc->qhc", weights, v)

    def _attend_absorbed(self, q, kv_in, distance, mask, rel) -> Float[Array, "q heads head_dim"]:
        """The same attention without projecting keys, values or positions (only queries and the output).

        With `n_j` the normalised input at key `j`, `k_j = W_k n_j + b_k` and `r_d = W_R s_d + b_R` per head:
        `(q + u)·k_j = (W_kᵀ (q + u))·n_j + (q + u)·b_k` and `(q + v)·r_d = (W_Rᵀ (q + v))·s_d + (q + v)·b_R`.
        The bias products are the same for every key of a (head, query) row, and the softmax ignores a
        constant added to a row, so they are dropped. Values: the weights sum to 1, so
        `Σ_j a_j (W_v n_j + b_v) = W_v (Σ_j a_j n_j) + b_v`. A step thus costs O(window_mem · heads · embed)
        for attention plus one query-sized projection each way, however long the cache, and the cache
        stays the layer inputs: keys follow the current parameters (no stale projected keys after an update).
        """
        heads, head_dim = self.num_heads, q.shape[-1]
        w_kv = self.key_value.weight.reshape(2, heads, head_dim, -1)  # rows: (key|value, head, channel)
        w_pos = self.pos.weight.reshape(heads, head_dim, -1)
        q_content = jnp.einsum("qhc,hce->qhe", q + self.content_bias[None], w_kv[0])
        q_pos = jnp.einsum("qhc,hce->qhe", q + self.pos_bias[None], w_pos)
        content = jnp.einsum("qhe,ke->hqk", q_content, kv_in)
        by_distance = jnp.einsum("qhe,de->hqd", q_pos, rel)
        weights = self._weights(content, by_distance, distance, mask, head_dim)
        mixed = jnp.einsum("hqk,ke->qhe", weights, kv_in)  # attention-averaged normalised inputs, per head
        b_v = self.key_value.bias.reshape(2, heads, head_dim)[1]
        return jnp.einsum("qhe,hce->qhc", mixed, w_kv[1]) + b_v[None]

    @staticmethod
    def _weights(content, by_distance, distance, mask, head_dim) -> Float[Array, "heads q k"]:
        heads = content.shape[0]
        index = jnp.broadcast_to(jnp.clip(distance, 0, by_distance.shape[-1] - 1), (heads, *distance.shape))
        position = jnp.take_along_axis(by_distance, index, axis=2)
        scores = (content + position) / math.sqrt(head_dim)
        # Every query can see itself, so no row is fully masked and the softmax is well defined.
        return jax.nn.softmax(jnp.where(mask, scores, -jnp.inf), axis=-1)


class TransformerXL(AbstractMemory[TrXLCarry]):
    """Gated Transformer-XL: `Dense(in, embed)`, then `num_layers` GTrXL blocks; `out_size == embed_size`.

    Sequences are cut into windows of `window_grad` steps (a shorter last window when `time` is not a
    multiple of it, e.g. `time == 1` in rollouts); each window attends to the cache and to itself.

    `attention` chooses how attention is computed, never what: `"projected"` projects the keys and values
    of the whole cache at every call (the textbook form); `"absorbed"` folds those projections into the
    query and the output, so a rollout step costs O(window_mem · heads · embed) instead of
    O(window_mem · embed · qkv); `"auto"` (default) picks the cheaper per call (always absorbed for one step).
    The outputs and gradients agree up to float rounding, and the carry is the same.
    """

    encoder: Dense
    blocks: tuple[_Block, ...]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)
    num_layers: int = eqx.field(static=True)
    window_mem: int = eqx.field(static=True)
    window_grad: int = eqx.field(static=True)
    attention: str = eqx.field(static=True)

    def __init__(
        self,
        in_size: int,
        *,
        key: PRNGKeyArray,
        embed_size: int = 256,
        num_heads: int = 8,
        num_layers: int = 2,
        qkv_features: int = 256,
        window_mem: int = 128,
        window_grad: int = 64,
        gating: bool = True,
        gating_bias: float = 2.0,
        attention: str = "auto",
    ):
        if attention not in ("auto", "absorbed", "projected"):
            raise ValueError(f"attention must be 'auto', 'absorbed' or 'projected', got {attention!r}")
        if window_mem < 1 or window_grad < 1 or num_layers < 1:
            raise ValueError(
                f"window_mem ({window_mem}), window_grad ({window_grad}) and num_layers ({num_layers}) "
                "must all be at least 1"
            )
        k_enc, *k_blocks = jax.random.split(key, num_layers + 1)
        self.in_size = in_size
        self.out_size = embed_size
        self.num_layers = num_layers
        self.window_mem = window_mem
        self.window_grad = window_grad
        self.attention = attention
        self.encoder = Dense(in_size, embed_size, key=k_enc, scale=1.0)
        self.blocks = tuple(
            _Block(embed_size, num_heads, qkv_features, gating, gating_bias, key=k) for k in k_blocks
        )

    @staticmethod
    def check_window(num_steps: int, window_grad: int) -> None:
        """Training replays `num_steps`-long segments in windows of `window_grad`: they must divide evenly."""
        if num_steps % window_grad != 0:
            raise ValueError(
                f"num_steps ({num_steps}) must be a multiple of window_grad ({window_grad}): choose "
                f"window_grad among the divisors of num_steps, or num_steps a multiple of {window_grad}"
            )

    def init_carry(self) -> TrXLCarry:
        return TrXLCarry(
            memory=jnp.zeros((self.num_layers, self.window_mem, self.out_size), jnp.float32),
            valid=jnp.zeros((self.window_mem,), bool),
        )

    def _window(
        self, carry: TrXLCarry, x: Float[Array, "w embed"], starts: Bool[Array, " w"]
    ) -> tuple[TrXLCarry, Float[Array, "w embed"]]:
        m, w = self.window_mem, x.shape[0]
        # Episode index of every position in [cache; window]: cached steps of the current episode are 0, the
        # others −1 (never visible); each start in the window opens a new index. Same index = same episode.
        episode = jnp.cumsum(starts.astype(jnp.int32))
        episode_all = jnp.concatenate([jnp.where(carry.valid, 0, -1), episode])
        distance = (m + jnp.arange(w))[:, None] - jnp.arange(m + w)[None, :]
        # Causal, at most window_mem steps back (what a single step sees), and never into an earlier episode.
        mask = (distance >= 0) & (distance <= m) & (episode_all[None, :] == episode[:, None])
        rel = _sinusoid(jnp.arange(m + 1), self.out_size)
        absorb = {"auto": None, "absorbed": True, "projected": False}[self.attention]
        inputs = []
        for block, mem in zip(self.blocks, carry.memory):
            inputs.append(jnp.concatenate([mem, x])[w:])  # this layer's inputs at the last window_mem steps
            x = block(x, mem, distance, mask, rel, absorb)
        new = TrXLCarry(
            memory=jax.lax.stop_gradient(jnp.stack(inputs)),
            valid=(episode_all == episode[-1])[w:],
        )
        return new, x

    def __call__(
        self, carry: TrXLCarry, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[TrXLCarry, Float[Array, "time out_size"]]:
        check_inputs(self, xs, starts)
        carry = jax.lax.stop_gradient(carry)  # truncated backpropagation: never into the saved cache
        x = self.encoder(xs)
        time, wg = xs.shape[0], self.window_grad
        full, rest = divmod(time, wg)
        outs = []
        if full:
            carry, ys = jax.lax.scan(
                lambda c, inp: self._window(c, *inp),
                carry,
                (x[: full * wg].reshape(full, wg, -1), starts[: full * wg].reshape(full, wg)),
            )
            outs.append(ys.reshape(full * wg, -1))
        if rest:  # e.g. time == 1 in rollouts: one shorter window, same mask, same cache update
            carry, ys = self._window(carry, x[full * wg :], starts[full * wg :])
            outs.append(ys)
        return carry, jnp.concatenate(outs) if len(outs) > 1 else outs[0]
