"""The GRU recurrence fused into one Pallas kernel for the forward pass and one for the backward pass.

PPO's replay runs the GRU over whole sequences (128 steps), forward and backward; with `jax.lax.scan` every time step
is a few tiny GPU kernels, so the sequential loop, not arithmetic, bounds the update. Here the loop over time runs
inside one kernel launch (per direction): the hidden state and the recurrent weights stay on chip, and each step reads
its input projections and writes its output by indexing the refs with the loop counter (`ref[t]`, a dynamic row).

`fused_recurrence(weight_hh, bias_hn, gates_x, starts, carry)` computes, for one unbatched sequence (gate order r, z, n
as in `pobax.memory._gru.GRU`):

    for t: h = where(starts[t], 0, h); gh = weight_hh @ h
           r = σ(gx[t, :H] + gh[:H]); z = σ(gx[t, H:2H] + gh[H:2H]); n = tanh(gx[t, 2H:] + r ⊙ (gh[2H:] + bias_hn))
           h = (1 − z) ⊙ n + z ⊙ h; ys[t] = h
    return h, ys

The kernels are the time loops of `pobax.memory._gru.recurrence` (`FusedLoops`), the GRU's `jax.custom_vjp` shared
with the scan: the forward kernel also saves the gate activations; the backward kernel runs t = T−1 … 0 and produces
the gradients of the gate pre-activations and of the incoming carry; the weight gradient (one matmul over time) and
the bias gradient are computed outside the kernels, by `recurrence`, with ordinary XLA ops. `jax.vmap` over `pallas_call` adds
grid dimensions, one program per sequence, so the function can be vmapped over environments (unbatched weights) and
over seeds (batched weights).

Backends: Triton on GPU; with `interpret=True` (what `GRU` passes off the GPU) the kernels run in Pallas' interpret
mode, slowly — that is for testing. The matrix-vector products are broadcast-multiply-and-sum (Triton's `dot` needs tiles of at least
16 × 16), and every block is a power of two in each dimension (a Triton requirement): the gates are split into three
(H, H) weights and three (T, H) input arrays in the wrapper. See `fused_supported` for the sizes allowed.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from ._gru import recurrence

try:  # Triton compiler parameters (number of warps); absent from builds without GPU Pallas support
    from jax.experimental.pallas import triton as _pltriton
except ImportError:  # pragma: no cover
    _pltriton = None

#: Smallest sequence length the fused kernels are used for (the rollout's T = 1 keeps the scan).
MIN_TIME = 8
#: Hidden-size range of the fused kernels. The three (H, H) recurrent weights are held in registers for the whole
#: loop. Compiled offline for sm_90 (Triton 3.9, the kernels' Triton IR as Pallas emits it): no register spills up to
#: H = 64 (H = 32: 128 registers/thread at 2 warps; H = 64: 234 at 4 warps), small spills at H = 128 even with 16
#: warps (~200 bytes/thread). Larger sizes would spill heavily; there the scan's batched matmul per step is the
#: better choice anyway.
MIN_HIDDEN, MAX_HIDDEN = 8, 128
#: Triton software-pipelining stages. The kernels prefetch the next step's inputs by hand (loaded one iteration
#: ahead and carried through the loop), so Triton's own pipelining is not needed.
NUM_STAGES: int = 1


def _is_pow2(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def fused_supported(time: int, hidden: int) -> bool:
    """Whether the fused kernels handle a sequence of `time` steps and hidden size `hidden`: both powers of two,
    `time >= MIN_TIME` (8) and `MIN_HIDDEN <= hidden <= MAX_HIDDEN` (8 … 128)."""
    return _is_pow2(time) and _is_pow2(hidden) and time >= MIN_TIME and MIN_HIDDEN <= hidden <= MAX_HIDDEN


def _num_warps(hidden: int) -> int:
    return {8: 1, 16: 1, 32: 2, 64: 4}.get(hidden, 16)


def _call(kernel, out_shape, config: tuple[bool, int, int], name: str):
    interpret, num_warps, num_stages = config
    params = None
    if not interpret and _pltriton is not None:
        params = _pltriton.CompilerParams(num_warps=num_warps, num_stages=num_stages)
    return pl.pallas_call(kernel, out_shape=out_shape, interpret=interpret, compiler_params=params, name=name)


def per_gate(x, gates: int, axis: int) -> list:
    """`x` (a weight's rows or a sequence's columns, gate after gate) split into one float32 block per gate: the
    kernels take each gate's block as its own power-of-two array."""
    return jnp.split(x.astype(jnp.float32), gates, axis=axis)


def rows(keep, width: int):
    """A per-step vector (T,) as float32 rows (T, width), one row per step, as the kernels index them (`ref[t]`)."""
    return jnp.broadcast_to(keep.astype(jnp.float32)[:, None], (keep.shape[0], width))


def _matvec(w, v):
    """`w @ v` for an (H, H) weight and an (H,) vector, as broadcast-multiply-and-sum."""
    return jnp.sum(w * v[None, :], axis=1)


def _fwd_kernel(save: bool, wr_ref, wz_ref, wn_ref, bhn_ref, gxr_ref, gxz_ref, gxn_ref, keep_ref, h0_ref,
                hT_ref, ys_ref, *res_refs):
    time = ys_ref.shape[0]
    wr, wz, wn, bhn = wr_ref[...], wz_ref[...], wn_ref[...], bhn_ref[...]

    def load(t):  # what step t reads besides the hidden state
        return gxr_ref[t], gxz_ref[t], gxn_ref[t], keep_ref[t]

    def step(t, state):
        h, (gxr, gxz, gxn, keep) = state
        nxt = load(jnp.minimum(t + 1, time - 1))  # prefetch: independent of h, so its latency overlaps this step
        hp = h * keep  # the reset: keep is 0 where the sequence starts
        r = jax.nn.sigmoid(gxr + _matvec(wr, hp))
        z = jax.nn.sigmoid(gxz + _matvec(wz, hp))
        ghn = _matvec(wn, hp) + bhn
        n = jnp.tanh(gxn + r * ghn)
        h = (1.0 - z) * n + z * hp
        ys_ref[t] = h
        if save:
            r_ref, z_ref, n_ref, ghn_ref = res_refs
            r_ref[t] = r
            z_ref[t] = z
            n_ref[t] = n
            ghn_ref[t] = ghn
        return h, nxt

    h, _ = jax.lax.fori_loop(0, time, step, (h0_ref[...], load(0)))
    hT_ref[...] = h


def _bwd_kernel(wr_ref, wz_ref, wn_ref, keep_ref, r_ref, z_ref, n_ref, ghn_ref, hp_ref, dys_ref, dhT_ref,
                dar_ref, daz_ref, dan_ref, dh0_ref):
    time = dys_ref.shape[0]
    wr, wz, wn = wr_ref[...], wz_ref[...], wn_ref[...]

    def load(t):
        return dys_ref[t], r_ref[t], z_ref[t], n_ref[t], ghn_ref[t], hp_ref[t], keep_ref[t]

    def step(i, state):
        dh, (dy, r, z, n, ghn, hp, keep) = state
        t = time - 1 - i
        nxt = load(jnp.maximum(t - 1, 0))  # prefetch the previous step's saved values
        dh = dh + dy
        dan = dh * (1.0 - z) * (1.0 - n * n)  # d tanh pre-activation
        daz = dh * (hp - n) * z * (1.0 - z)  # d z pre-activation
        dar = dan * ghn * r * (1.0 - r)  # d r pre-activation
        dghn = dan * r  # d (W_hn h + b_hn)
        dar_ref[t] = dar
        daz_ref[t] = daz
        dan_ref[t] = dan
        # One reduction for the three transposed products W_r^T dar + W_z^T daz + W_n^T dghn.
        back = jnp.sum(wr * dar[:, None] + wz * daz[:, None] + wn * dghn[:, None], axis=0)
        return (dh * z + back) * keep, nxt  # no gradient flows past a reset

    dh, _ = jax.lax.fori_loop(0, time, step, (dhT_ref[...], load(time - 1)))
    dh0_ref[...] = dh


@dataclasses.dataclass(frozen=True)
class FusedLoops:
    """The time loops of `pobax.memory._gru.recurrence` as the Pallas kernels above; `config`: (interpret,
    num_warps, num_stages). The gates are split into three (H, H) weights and three (T, H) inputs for them."""

    config: tuple[bool, int, int]

    def forward(self, save, weight_hh, bias_hn, gates_x, starts, carry):
        time, h = gates_x.shape[0], carry.shape[0]
        seq = jax.ShapeDtypeStruct((time, h), jnp.float32)
        out_shape = [jax.ShapeDtypeStruct((h,), jnp.float32), seq] + [seq] * (4 if save else 0)
        outs = _call(functools.partial(_fwd_kernel, save), out_shape, self.config, "gru_fused_fwd")(
            *per_gate(weight_hh, 3, 0), bias_hn.astype(jnp.float32), *per_gate(gates_x, 3, 1),
            rows(jnp.where(starts, 0.0, 1.0), h), carry.astype(jnp.float32))
        return outs[0], outs[1], (tuple(outs[2:]) if save else None)

    def backward(self, weight_hh, keep, hprev, saved, dys, d_last):
        time, h = dys.shape
        seq = jax.ShapeDtypeStruct((time, h), jnp.float32)
        out_shape = [seq, seq, seq, jax.ShapeDtypeStruct((h,), jnp.float32)]
        return _call(_bwd_kernel, out_shape, self.config, "gru_fused_bwd")(
            *per_gate(weight_hh, 3, 0), rows(keep, h), *saved, hprev, dys, d_last)


def fused_recurrence(weight_hh, bias_hn, gates_x, starts, carry, *, interpret: bool = False,
                     num_warps: int | None = None, num_stages: int | None = None):
    """The GRU recurrence of one sequence with fused Pallas kernels; returns `(carry_out, ys)`.

    weight_hh: (3H, H), bias_hn: (H,), gates_x: (T, 3H) input projections with their biases (order r, z, n),
    starts: (T,) bool (reset the carry to zeros before that step), carry: (H,). Requires `fused_supported(T, H)`.
    Triton kernels (GPUs), or with `interpret` Pallas' interpreter (any platform, slowly; the
    memories pass `interpret` off the GPU). Float32 throughout; `starts` gets no gradient.
    `num_warps` / `num_stages` override `_num_warps(H)` / `NUM_STAGES` (Triton only; for benchmarking).
    """
    time, h = gates_x.shape[0], carry.shape[0]
    if weight_hh.shape != (3 * h, h) or bias_hn.shape != (h,) or gates_x.shape != (time, 3 * h) \
            or starts.shape != (time,):
        raise ValueError(f"fused_recurrence: inconsistent shapes weight_hh {weight_hh.shape}, bias_hn "
                         f"{bias_hn.shape}, gates_x {gates_x.shape}, starts {starts.shape}, carry {carry.shape}")
    if not fused_supported(time, h):
        raise ValueError(f"fused_recurrence: unsupported sizes T={time}, H={h} (see fused_supported)")
    config = (bool(interpret), num_warps or _num_warps(h), num_stages or NUM_STAGES)
    return recurrence(FusedLoops(config), weight_hh, bias_hn, gates_x, starts.astype(bool), carry)
