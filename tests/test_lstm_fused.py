"""The fused (Pallas) LSTM recurrence against the library's scan (`lstm_recurrence`, what `LSTM` runs otherwise):
outputs, final h and c, and all gradients, under jit and vmap over environments (shared weights) and seeds (batched
weights). Off the GPU the kernels run in Pallas' interpret mode (`interpret=True`, what `LSTM` passes there).

Precision, as for the GRU (tests/test_gru_fused.py): the fused side at JAX's default matmul precision, the scan
reference at float32 precision (`jax.default_matmul_precision("highest")`; a GPU's default is TF32). The kernels
compute in float32, so outputs and the gradients of gates_x, h0 and c0 agree to 1e-5 and 1e-4. The weight gradient
Σ_t outer(da_t, h_{t−1}) is the fused side's one matrix product outside the kernels: on a GPU its tolerance adds
2^-10 · Σ_t |da_t| · max|h| (TF32 inputs; da is the gradient of gates_x, |h| ≤ max(1, |h0|) as h = o ⊙ tanh(c))."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax._backend import platform_of
from pobax.agent import TrainConfig
from pobax.agent._ppo import make_model
from pobax.env import make
from pobax.memory import LSTM
from pobax.memory._lstm import lstm_recurrence
from pobax.memory._lstm_fused import fused_lstm_recurrence as _fused_lstm_recurrence

from _precision import TF32_EPS, at_float32_precision

T, H = 16, 8
PLATFORM = platform_of()
MATMUL_EPS = TF32_EPS if PLATFORM == "gpu" else 0.0  # a matrix product's relative error at the default precision
fused_lstm_recurrence = functools.partial(_fused_lstm_recurrence, interpret=PLATFORM != "gpu")


def _inputs(key, batch=(), weight_batch=()):
    ks = jax.random.split(key, 5)
    w = jax.random.normal(ks[0], (*weight_batch, 4 * H, H)) * 0.6
    gx = jax.random.normal(ks[1], (*batch, T, 4 * H))
    h0, c0 = jax.random.normal(ks[2], (*batch, H)), jax.random.normal(ks[3], (*batch, H))  # a carry that is not zero
    starts = jax.random.bernoulli(ks[4], 0.15, (*batch, T))
    return w, gx, starts, h0, c0


def _outputs_and_grads(f):
    """One jitted function for the outputs and the gradients w.r.t. weight_hh, gates_x, h0 and c0, of a loss that
    touches the outputs at every step (with different weights) and the final h and c."""
    def loss(w, gx, starts, h0, c0):
        h, c, ys = f(w, gx, starts, h0, c0)
        weights = jnp.linspace(0.5, 2.0, ys.size).reshape(ys.shape)
        return jnp.sum(jnp.sin(ys) * weights) + jnp.sum(h**2) + jnp.sum(jnp.cos(c))

    return jax.jit(lambda *args: (f(*args), jax.grad(loss, argnums=(0, 1, 3, 4))(*args)))


def _reference(f):
    """`_outputs_and_grads(f)` at float32 matmul precision (see the module's docstring)."""
    return at_float32_precision(_outputs_and_grads(f))


def _assert_close(got, want, h0):
    (out_f, grads_f), (out_r, grads_r) = got, want
    for name, a, b in zip(("h", "c", "ys"), out_f, out_r):
        np.testing.assert_allclose(a, b, atol=1e-5, err_msg=name)
    d_gx = np.abs(np.asarray(grads_r[1]))
    h_max = max(1.0, float(jnp.abs(h0).max()))
    weight_tol = 1e-4 + MATMUL_EPS * h_max * d_gx.reshape(-1, d_gx.shape[-1]).sum(0)[:, None]
    for name, a, b, tol in zip(("weight_hh", "gates_x", "h0", "c0"), grads_f, grads_r, (weight_tol, 1e-4, 1e-4, 1e-4)):
        assert a.shape == b.shape, name
        assert name in ("h0", "c0") or float(jnp.abs(b).max()) > 1e-3, name  # a gradient there to compare
        diff = np.abs(np.asarray(a) - np.asarray(b))
        assert np.all(diff <= tol), f"{name}: largest difference {diff.max():.3g}"


def test_single_sequence_matches_the_scan_through_resets():
    fused, ref = _outputs_and_grads(fused_lstm_recurrence), _reference(lstm_recurrence)
    w, gx, _, h0, c0 = _inputs(jax.random.key(0))
    for first, middle in [(False, False), (True, False), (False, True)]:
        starts = jnp.zeros(T, bool).at[0].set(first).at[7].set(middle)
        got = fused(w, gx, starts, h0, c0)
        _assert_close(got, ref(w, gx, starts, h0, c0), h0)
        carry_grads = jnp.concatenate(got[1][2:])
        # a start at step 0 forgets the incoming carry: no gradient reaches it; otherwise one does
        assert not jnp.any(carry_grads) if first else float(jnp.abs(carry_grads).max()) > 1e-3


def test_vmapped_over_environments_and_seeds():
    w, gx, starts, h0, c0 = _inputs(jax.random.key(1), batch=(2, 3), weight_batch=(2,))

    def nested(f):
        return jax.vmap(jax.vmap(f, in_axes=(None, 0, 0, 0, 0)))

    _assert_close(_outputs_and_grads(nested(fused_lstm_recurrence))(w, gx, starts, h0, c0),
                  _reference(nested(lstm_recurrence))(w, gx, starts, h0, c0), h0)


def test_unsupported_sizes_are_refused_and_the_module_falls_back_to_the_scan():
    w, gx, starts, h0, c0 = _inputs(jax.random.key(2))
    with pytest.raises(ValueError, match="unsupported sizes"):
        fused_lstm_recurrence(w, gx[:12], starts[:12], h0, c0)
    xs = jax.random.normal(jax.random.key(3), (T, 5))
    steps = jnp.zeros(T, bool).at[5].set(True)
    fused, dot = (LSTM(5, H, key=jax.random.key(4), impl=impl, platform=PLATFORM) for impl in ("fused", "dot"))
    for n in (T, 1):  # the whole sequence through the kernels; one step (the rollout) through the scan
        got, want = fused(fused.init_carry(), xs[:n], steps[:n]), dot(dot.init_carry(), xs[:n], steps[:n])
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(a, b, atol=1e-5)
    with pytest.raises(ValueError, match="LSTM impl must be one of"):
        LSTM(5, H, key=jax.random.key(4), impl="einsum")


def test_the_training_loop_builds_the_lstm_with_its_unroll():
    env = make("tmaze_3")
    model = make_model(TrainConfig(env="tmaze_3", memory="lstm", hidden_size=8, unroll=3), env, jax.random.key(0))
    assert isinstance(model.memory, LSTM) and model.memory.unroll == 3
