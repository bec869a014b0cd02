"""The fused (Pallas) GRU recurrence against the library's scan (`scan_recurrence`, what `GRU` runs otherwise):
outputs, final carry and all gradients, under jit and (nested) vmap. Off the GPU the kernels run in Pallas' interpret
mode (`interpret=True`, what `GRU` passes there).

Precision. The fused side runs at JAX's default matmul precision, as training runs it. The scan reference is computed
at float32 precision (`jax.default_matmul_precision("highest")`): at the default precision a GPU computes its
matrix products, batched ones under vmap included, in TF32 (10-bit mantissa), whose rounding compounds through the
recurrence. The kernels compute in float32 (multiply-sums, no matrix units), so outputs and the gradients of gates_x,
bias_hn and the carry agree to float32 rounding over 16 steps: 1e-5 and 1e-4. One matrix product of the fused side
runs outside the kernels, the weight gradient Σ_t outer(d_gh_t, h_{t−1}), so on a GPU its inputs are rounded to TF32
(relative error ≤ 2^-11 each, ≤ 2^-10 per product): its tolerance adds 2^-10 · Σ_t |d_gh_t| · max|h|, with
|d_gh| ≤ |d gates_x| elementwise (r ∈ (0, 1)) and |h| ≤ max(1, |carry|) (each h is a convex combination of the
previous one and tanh), both taken from the reference (`_weight_grad_tolerance`)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax._backend import platform_of
from pobax.memory._gru import scan_recurrence
from pobax.memory._gru_fused import fused_recurrence as _fused_recurrence
from pobax.memory._gru_fused import fused_supported

from _precision import TF32_EPS, at_float32_precision

T, H = 16, 8
ATOL_OUT, ATOL_GRAD = 1e-5, 1e-4
PLATFORM = platform_of()
#: Relative error of a matrix product at the default precision: TF32 inputs on GPUs, float32 elsewhere (0: the
#: float32 tolerances cover it).
MATMUL_EPS = TF32_EPS if PLATFORM == "gpu" else 0.0
fused_recurrence = functools.partial(_fused_recurrence, interpret=PLATFORM != "gpu")


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


def _reference(f):
    """`_outputs_and_grads(f)` at float32 matmul precision (see the module's docstring)."""
    return at_float32_precision(_outputs_and_grads(f))


def _weight_grad_tolerance(want, carry):
    """ATOL_GRAD plus the bound of the TF32 rounding of the fused side's weight-gradient product (module docstring):
    2^-10 · max|h| · Σ over time (and over the sequences sharing the weights) of |d gates_x|, per weight row."""
    d_gx = np.abs(np.asarray(want[1][2]))
    h_max = max(1.0, float(np.abs(np.asarray(carry)).max()))
    return ATOL_GRAD + MATMUL_EPS * h_max * d_gx.reshape(-1, d_gx.shape[-1]).sum(0)[:, None]


def _assert_close(got, want, carry):
    (out_f, grads_f), (out_r, grads_r) = got, want
    for a, b in zip(out_f, out_r):
        np.testing.assert_allclose(a, b, atol=ATOL_OUT)
    tolerances = (_weight_grad_tolerance(want, carry), ATOL_GRAD, ATOL_GRAD, ATOL_GRAD)
    for name, a, b, tol in zip(("weight_hh", "bias_hn", "gates_x", "carry"), grads_f, grads_r, tolerances):
        assert a.shape == b.shape, name
        assert np.all(np.abs(np.asarray(a) - np.asarray(b)) <= tol), \
            f"{name}: largest difference {np.abs(np.asarray(a) - np.asarray(b)).max():.3g}"


def test_single_sequence_matches_the_scan():
    fused, ref = _outputs_and_grads(fused_recurrence), _reference(scan_recurrence)
    w, b, gx, _, carry = _inputs(jax.random.key(0))
    for first, middle in [(False, False), (True, False), (False, True), (True, True)]:
        starts = jnp.zeros(T, bool).at[0].set(first).at[7].set(middle)
        _assert_close(fused(w, b, gx, starts, carry), ref(w, b, gx, starts, carry), carry)


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
    _assert_close(_outputs_and_grads(vm(fused_recurrence))(*args), _reference(vm(scan_recurrence))(*args), carry)


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
    _assert_close(_outputs_and_grads(nested(fused_recurrence))(*args), _reference(nested(scan_recurrence))(*args),
                  carry)


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
        gru = G.GRU(5, 16, key=jax.random.key(0), impl=impl, platform=PLATFORM)

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
