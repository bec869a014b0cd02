"""The fused (Pallas) LSTM recurrence against the library's scan (`lstm_recurrence`, what `LSTM` runs otherwise):
outputs, final h and c, and all gradients, under jit and vmap over environments (shared weights) and seeds (batched
weights). On the CPU the kernels run in Pallas' interpret mode. On a GPU, run them with
JAX_DEFAULT_MATMUL_PRECISION=highest: the scan reference's batched matrix products are TF32 otherwise, and the vmapped
comparisons miss 1e-5 (H200)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax.agent import TrainConfig
from pobax.agent._ppo import make_model
from pobax.env import make
from pobax.memory import LSTM
from pobax.memory._lstm import lstm_recurrence
from pobax.memory._lstm_fused import fused_lstm_recurrence

T, H = 16, 8


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


def _assert_close(got, want):
    (out_f, grads_f), (out_r, grads_r) = got, want
    for name, a, b in zip(("h", "c", "ys"), out_f, out_r):
        np.testing.assert_allclose(a, b, atol=1e-5, err_msg=name)
    for name, a, b in zip(("weight_hh", "gates_x", "h0", "c0"), grads_f, grads_r):
        assert a.shape == b.shape, name
        assert name in ("h0", "c0") or float(jnp.abs(b).max()) > 1e-3, name  # a gradient there to compare
        np.testing.assert_allclose(a, b, atol=1e-4, err_msg=name)


def test_single_sequence_matches_the_scan_through_resets():
    fused, ref = _outputs_and_grads(fused_lstm_recurrence), _outputs_and_grads(lstm_recurrence)
    w, gx, _, h0, c0 = _inputs(jax.random.key(0))
    for first, middle in [(False, False), (True, False), (False, True)]:
        starts = jnp.zeros(T, bool).at[0].set(first).at[7].set(middle)
        got = fused(w, gx, starts, h0, c0)
        _assert_close(got, ref(w, gx, starts, h0, c0))
        carry_grads = jnp.concatenate(got[1][2:])
        # a start at step 0 forgets the incoming carry: no gradient reaches it; otherwise one does
        assert not jnp.any(carry_grads) if first else float(jnp.abs(carry_grads).max()) > 1e-3


def test_vmapped_over_environments_and_seeds():
    w, gx, starts, h0, c0 = _inputs(jax.random.key(1), batch=(2, 3), weight_batch=(2,))

    def nested(f):
        return jax.vmap(jax.vmap(f, in_axes=(None, 0, 0, 0, 0)))

    _assert_close(_outputs_and_grads(nested(fused_lstm_recurrence))(w, gx, starts, h0, c0),
                  _outputs_and_grads(nested(lstm_recurrence))(w, gx, starts, h0, c0))


def test_unsupported_sizes_are_refused_and_the_module_falls_back_to_the_scan():
    w, gx, starts, h0, c0 = _inputs(jax.random.key(2))
    with pytest.raises(ValueError, match="unsupported sizes"):
        fused_lstm_recurrence(w, gx[:12], starts[:12], h0, c0)
    xs = jax.random.normal(jax.random.key(3), (T, 5))
    steps = jnp.zeros(T, bool).at[5].set(True)
    fused, dot = (LSTM(5, H, key=jax.random.key(4), impl=impl) for impl in ("fused", "dot"))
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
