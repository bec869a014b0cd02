"""The fused (Pallas) GRU recurrence against the library's scan (`scan_recurrence`, what `GRU` runs otherwise):
outputs, final carry and all gradients, under jit and (nested) vmap. On the CPU the kernels run in Pallas' interpret
mode. On a GPU, run them with JAX_DEFAULT_MATMUL_PRECISION=highest: the scan reference's batched matrix products are
TF32 otherwise, and the vmapped comparisons miss 1e-5 (H200)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax.memory._gru import scan_recurrence
from pobax.memory._gru_fused import fused_recurrence, fused_supported

T, H = 16, 8
ATOL_OUT, ATOL_GRAD = 1e-5, 1e-4


def _inputs(key, batch=(), weight_batch=()):
    ks = jax.random.split(key, 5)
    w = jax.random.normal(ks[0], (*weight_batch, 3 * H, H)) * 0.6
    b = jax.random.normal(ks[1], (*weight_batch, H)) * 0.3
    gx = jax.random.normal(ks[2], (*batch, T, 3 * H))
    carry = jax.random.normal(ks[3], (*batch, H))  # a non-zero incoming carry
    starts = jax.random.bernoulli(ks[4], 0.15, (*batch, T))
    return w, b, gx, starts, carry


def _loss(f):
    """A loss touching the outputs at every step (with different weights) and the final carry."""
    def loss(w, b, gx, starts, carry):
        last, ys = f(w, b, gx, starts, carry)
        weights = jnp.linspace(0.5, 2.0, ys.size).reshape(ys.shape)
        return jnp.sum(jnp.sin(ys) * weights) + jnp.sum(last**2)

    return loss


def _outputs_and_grads(f):
    """One jitted function for the outputs and the gradients w.r.t. weight_hh, bias_hn, gates_x and carry."""
    return jax.jit(lambda *args: (f(*args), jax.grad(_loss(f), argnums=(0, 1, 2, 4))(*args)))


def _assert_close(got, want):
    (out_f, grads_f), (out_r, grads_r) = got, want
    for a, b in zip(out_f, out_r):
        np.testing.assert_allclose(a, b, atol=ATOL_OUT)
    for name, a, b in zip(("weight_hh", "bias_hn", "gates_x", "carry"), grads_f, grads_r):
        assert a.shape == b.shape, name
        np.testing.assert_allclose(a, b, atol=ATOL_GRAD, err_msg=name)


def test_single_sequence_matches_the_scan():
    fused, ref = _outputs_and_grads(fused_recurrence), _outputs_and_grads(scan_recurrence)
    w, b, gx, _, carry = _inputs(jax.random.key(0))
    for first, middle in [(False, False), (True, False), (False, True), (True, True)]:
        starts = jnp.zeros(T, bool).at[0].set(first).at[7].set(middle)
        _assert_close(fused(w, b, gx, starts, carry), ref(w, b, gx, starts, carry))


def test_carry_gradient_only_through_steps_before_the_first_start():
    w, b, gx, _, carry = _inputs(jax.random.key(1))
    grad = jax.jit(jax.grad(_loss(fused_recurrence), argnums=4))
    g = grad(w, b, gx, jnp.zeros(T, bool).at[0].set(True), carry)
    np.testing.assert_array_equal(g, jnp.zeros_like(g))
    g = grad(w, b, gx, jnp.zeros(T, bool).at[3].set(True), carry)
    assert jnp.abs(g).max() > 1e-3


def test_vmap_over_sequences_with_shared_weights():
    w, b, gx, starts, carry = _inputs(jax.random.key(2), batch=(3,))
    starts = starts.at[:, 0].set(True).at[1, 0].set(False)
    vm = lambda f: jax.vmap(f, in_axes=(None, None, 0, 0, 0))  # noqa: E731
    args = (w, b, gx, starts, carry)
    _assert_close(_outputs_and_grads(vm(fused_recurrence))(*args), _outputs_and_grads(vm(scan_recurrence))(*args))


def test_nested_vmap_with_batched_weights_and_time_major_inputs():
    """Seeds × environments, with the weights batched over seeds and the sequences batched on axis 1 (as PPO's
    minibatches are)."""
    seeds, envs = 2, 3
    w, b, gx, starts, carry = _inputs(jax.random.key(3), batch=(seeds, envs), weight_batch=(seeds,))
    gx, starts = jnp.swapaxes(gx, 1, 2), jnp.swapaxes(starts, 1, 2)  # (seeds, T, envs, …)

    def nested(f):
        inner = jax.vmap(f, in_axes=(None, None, 1, 1, 0), out_axes=(0, 1))
        return jax.vmap(inner)

    args = (w, b, gx, starts, carry)
    _assert_close(_outputs_and_grads(nested(fused_recurrence))(*args),
                  _outputs_and_grads(nested(scan_recurrence))(*args))


def test_fused_supported_sizes():
    assert fused_supported(128, 32) and fused_supported(8, 8) and fused_supported(128, 128)
    for t, h in [(1, 32), (4, 32), (100, 32), (128, 48), (128, 4), (128, 256), (127, 32)]:
        assert not fused_supported(t, h), (t, h)
    w, b, gx, starts, carry = _inputs(jax.random.key(4))
    with pytest.raises(ValueError):
        fused_recurrence(w, b, gx[:12], starts[:12], carry)


def test_gru_module_fused_equals_dot():
    import pobax.memory._gru as G

    xs = jax.random.normal(jax.random.key(1), (16, 5))
    starts = jnp.zeros(16, bool).at[0].set(True).at[7].set(True)
    carry = jax.random.normal(jax.random.key(2), (16,))

    def loss(m, c):  # a sequence without a start at t = 0: the carry gets a gradient too
        return jnp.sum(m(c, xs[::-1], starts.at[0].set(False))[1] ** 2)

    out = {}
    for impl in ("dot", "fused"):
        gru = G.GRU(5, 16, key=jax.random.key(0), impl=impl)

        def run(m, c):  # T = 1 (the rollout) keeps the scan.
            return m(c, xs, starts), jax.grad(loss, argnums=(0, 1))(m, c), m(c, xs[:1], starts[:1])

        out[impl] = jax.jit(run)(gru, carry)
        jaxpr = str(jax.make_jaxpr(run)(gru, carry))
        assert jaxpr.count("pallas_call") == (3 if impl == "fused" else 0)  # forward, grad's forward and backward
    (seq_d, (gm_d, gc_d), one_d), (seq_f, (gm_f, gc_f), one_f) = out["dot"], out["fused"]
    for a, b in zip(seq_d + one_d, seq_f + one_f):
        np.testing.assert_allclose(a, b, atol=1e-5)
    for name in ("weight_hh", "bias_hn", "weight_ih", "bias"):
        np.testing.assert_allclose(getattr(gm_d, name), getattr(gm_f, name), atol=1e-4, err_msg=name)
    np.testing.assert_allclose(gc_d, gc_f, atol=1e-4)
