"""The LSTM recurrence fused into one Pallas kernel for the forward pass and one for the backward pass.

The LSTM's counterpart of `pobax.memory._gru_fused` (read that module first: the same layout, launch and limits).
`fused_lstm_recurrence(weight_hh, gates_x, starts, h0, c0)` computes, for one unbatched sequence (gate order i, f,
g, o as in `pobax.memory.LSTM`):

    for t: h, c = where(starts[t], 0, (h, c)); a = gx[t] + weight_hh @ h
           i, f, o = σ(a_i), σ(a_f), σ(a_o); g = tanh(a_g); c = f ⊙ c + i ⊙ g; h = o ⊙ tanh(c); ys[t] = h
    return h, c, ys

The kernels are the time loops of `pobax.memory._lstm.recurrence` (`FusedLoops`), the LSTM's `jax.custom_vjp`
shared with the scan: the forward kernel also saves the gates and the cell each step started from; the backward
kernel runs t = T−1 … 0 carrying the gradients of `h` and `c`, and writes the gate pre-activations' gradients; the
weight gradient is one matrix product over time outside the kernels. The four (H, H) recurrent weights are held in
registers for the whole loop: `pobax._backend.lstm_impl` uses the kernels up to 32 wide.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp

from ._gru_fused import NUM_STAGES, _call, _matvec, _num_warps, fused_supported, per_gate, rows
from ._lstm import recurrence


def _fwd_kernel(save: bool, wi_ref, wf_ref, wg_ref, wo_ref, gxi_ref, gxf_ref, gxg_ref, gxo_ref, keep_ref, h0_ref,
                c0_ref, hT_ref, cT_ref, ys_ref, *res_refs):
    time = ys_ref.shape[0]
    wi, wf, wg, wo = wi_ref[...], wf_ref[...], wg_ref[...], wo_ref[...]

    def load(t):  # what step t reads besides the state
        return gxi_ref[t], gxf_ref[t], gxg_ref[t], gxo_ref[t], keep_ref[t]

    def step(t, state):
        h, c, (gxi, gxf, gxg, gxo, keep) = state
        nxt = load(jnp.minimum(t + 1, time - 1))  # prefetch: independent of the state
        hp, cp = h * keep, c * keep  # the reset: keep is 0 where the sequence starts
        i = jax.nn.sigmoid(gxi + _matvec(wi, hp))
        f = jax.nn.sigmoid(gxf + _matvec(wf, hp))
        g = jnp.tanh(gxg + _matvec(wg, hp))
        o = jax.nn.sigmoid(gxo + _matvec(wo, hp))
        c = f * cp + i * g
        h = o * jnp.tanh(c)
        ys_ref[t] = h
        if save:
            i_ref, f_ref, g_ref, o_ref, cin_ref = res_refs
            i_ref[t] = i
            f_ref[t] = f
            g_ref[t] = g
            o_ref[t] = o
            cin_ref[t] = cp
        return h, c, nxt

    h, c, _ = jax.lax.fori_loop(0, time, step, (h0_ref[...], c0_ref[...], load(0)))
    hT_ref[...] = h
    cT_ref[...] = c


def _bwd_kernel(wi_ref, wf_ref, wg_ref, wo_ref, keep_ref, i_ref, f_ref, g_ref, o_ref, cin_ref, dys_ref, dhT_ref,
                dcT_ref, dai_ref, daf_ref, dag_ref, dao_ref, dh0_ref, dc0_ref):
    time = dys_ref.shape[0]
    wi, wf, wg, wo = wi_ref[...], wf_ref[...], wg_ref[...], wo_ref[...]

    def load(t):
        return dys_ref[t], i_ref[t], f_ref[t], g_ref[t], o_ref[t], cin_ref[t], keep_ref[t]

    def step(k, state):
        dh, dc, (dy, i, f, g, o, cin, keep) = state
        t = time - 1 - k
        nxt = load(jnp.maximum(t - 1, 0))  # prefetch the previous step's saved values
        dh = dh + dy
        tc = jnp.tanh(f * cin + i * g)
        dc = dc + dh * o * (1.0 - tc * tc)
        dai = dc * g * i * (1.0 - i)
        daf = dc * cin * f * (1.0 - f)
        dag = dc * i * (1.0 - g * g)
        dao = dh * tc * o * (1.0 - o)
        dai_ref[t] = dai
        daf_ref[t] = daf
        dag_ref[t] = dag
        dao_ref[t] = dao
        # One reduction for the four transposed products W_i^T dai + W_f^T daf + W_g^T dag + W_o^T dao.
        back = jnp.sum(wi * dai[:, None] + wf * daf[:, None] + wg * dag[:, None] + wo * dao[:, None], axis=0)
        return back * keep, dc * f * keep, nxt  # no gradient flows past a reset

    dh, dc, _ = jax.lax.fori_loop(0, time, step, (dhT_ref[...], dcT_ref[...], load(time - 1)))
    dh0_ref[...] = dh
    dc0_ref[...] = dc


@dataclasses.dataclass(frozen=True)
class FusedLoops:
    """The time loops of `pobax.memory._lstm.recurrence` as the Pallas kernels above; `config`: (interpret,
    num_warps, num_stages). The gates are split into four (H, H) weights and four (T, H) inputs for them."""

    config: tuple[bool, int, int]

    def forward(self, save, weight_hh, gates_x, starts, h0, c0):
        time, h = gates_x.shape[0], h0.shape[0]
        vec, seq = jax.ShapeDtypeStruct((h,), jnp.float32), jax.ShapeDtypeStruct((time, h), jnp.float32)
        out_shape = [vec, vec, seq] + [seq] * (5 if save else 0)
        outs = _call(functools.partial(_fwd_kernel, save), out_shape, self.config, "lstm_fused_fwd")(
            *per_gate(weight_hh, 4, 0), *per_gate(gates_x, 4, 1), rows(jnp.where(starts, 0.0, 1.0), h),
            h0.astype(jnp.float32), c0.astype(jnp.float32))
        return outs[0], outs[1], outs[2], (tuple(outs[3:]) if save else None)

    def backward(self, weight_hh, keep, saved, dys, dh_last, dc_last):
        time, h = dys.shape
        vec, seq = jax.ShapeDtypeStruct((h,), jnp.float32), jax.ShapeDtypeStruct((time, h), jnp.float32)
        outs = _call(_bwd_kernel, [seq, seq, seq, seq, vec, vec], self.config, "lstm_fused_bwd")(
            *per_gate(weight_hh, 4, 0), rows(keep, h), *saved, dys.astype(jnp.float32),
            dh_last.astype(jnp.float32), dc_last.astype(jnp.float32))
        return jnp.concatenate(outs[:4], axis=1), outs[4], outs[5]


def fused_lstm_recurrence(weight_hh, gates_x, starts, h0, c0, *, interpret: bool = False,
                          num_warps: int | None = None, num_stages: int | None = None):
    """The LSTM recurrence of one sequence with fused Pallas kernels; returns `(h_last, c_last, ys)`.

    weight_hh: (4H, H), gates_x: (T, 4H) input projections with their biases (order i, f, g, o), starts: (T,) bool
    (reset h and c to zeros before that step), h0, c0: (H,). Requires `fused_supported(T, H)` (that of the GRU's
    kernels). Triton kernels (GPUs), or with `interpret` Pallas' interpreter (any platform, slowly; the
    memories pass `interpret` off the GPU). Float32 throughout; `starts` gets no
    gradient. `num_warps` / `num_stages` override the GRU kernels' choices (Triton only; for benchmarking).
    """
    time, h = gates_x.shape[0], h0.shape[0]
    if weight_hh.shape != (4 * h, h) or gates_x.shape != (time, 4 * h) or starts.shape != (time,) \
            or c0.shape != (h,):
        raise ValueError(f"fused_lstm_recurrence: inconsistent shapes weight_hh {weight_hh.shape}, gates_x "
                         f"{gates_x.shape}, starts {starts.shape}, h0 {h0.shape}, c0 {c0.shape}")
    if not fused_supported(time, h):
        raise ValueError(f"fused_lstm_recurrence: unsupported sizes T={time}, H={h} (see fused_supported)")
    config = (bool(interpret), num_warps or _num_warps(h), num_stages or NUM_STAGES)
    return recurrence(FusedLoops(config), weight_hh, gates_x, starts.astype(bool), h0, c0)
