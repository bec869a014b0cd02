import functools
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax.memory import GRU, Memoryless

T, IN, H = 12, 5, 8


def make(name, key):
    if name == "gru":
        return GRU(IN, H, key=key)
    if name == "gru_extra":
        return GRU(IN, H, key=key, extra_dense=True)
    return Memoryless(IN, H, key=key)


@pytest.mark.parametrize("name", ["gru", "gru_extra", "memoryless"])
def test_stepwise_equals_sequence_with_resets_under_jit_and_vmap(name):
    mem = make(name, jax.random.key(0))
    B = 3
    xs = jax.random.normal(jax.random.key(1), (B, T, IN))
    starts = jnp.zeros((B, T), bool).at[:, 0].set(True).at[0, 4].set(True).at[1, 7].set(True).at[2, 11].set(True)
    carry0 = jax.vmap(lambda _: mem.init_carry())(jnp.arange(B))
    # a non-trivial carry at the start, as in a rollout segment that continues an episode
    carry0 = jax.tree.map(lambda c: c + 0.3, carry0)
    starts = starts.at[2, 0].set(False)

    seq = jax.jit(jax.vmap(mem))
    carry_seq, ys_seq = seq(carry0, xs, starts)

    one = jax.jit(jax.vmap(lambda c, x, s: mem(c, x[None], s[None])))
    carry, outs = carry0, []
    for t in range(T):
        carry, y = one(carry, xs[:, t], starts[:, t])
        outs.append(y[:, 0])
    np.testing.assert_allclose(np.stack(outs, 1), ys_seq, atol=1e-5)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-5), carry, carry_seq)


def test_gru_reset_forgets_the_past():
    mem = GRU(IN, H, key=jax.random.key(0))
    xs = jax.random.normal(jax.random.key(1), (T, IN))
    starts = jnp.zeros(T, bool).at[0].set(True).at[6].set(True)
    _, ys = mem(mem.init_carry(), xs, starts)
    xs2 = xs.at[:6].set(-xs[:6])  # change the previous episode only
    _, ys2 = mem(mem.init_carry(), xs2, starts)
    np.testing.assert_allclose(ys[6:], ys2[6:], atol=1e-6)
    assert not np.allclose(ys[:6], ys2[:6])
    # without the reset the past leaks through
    _, ys3 = mem(mem.init_carry(), xs2, starts.at[6].set(False))
    assert not np.allclose(ys[6:], ys3[6:])


def test_gru_matches_closed_form_step():
    mem = GRU(IN, H, key=jax.random.key(2))
    x = jax.random.normal(jax.random.key(3), (1, IN))
    h = jax.random.normal(jax.random.key(4), (H,))
    _, y = mem(h, x, jnp.zeros(1, bool))
    a = jax.nn.relu(mem.pre(x))[0]
    gx = mem.weight_ih @ a + mem.bias
    gh = mem.weight_hh @ h
    r = jax.nn.sigmoid(gx[:H] + gh[:H])
    z = jax.nn.sigmoid(gx[H:2 * H] + gh[H:2 * H])
    n = np.tanh(gx[2 * H:] + r * (gh[2 * H:] + mem.bias_hn))
    np.testing.assert_allclose(y[0], (1 - z) * n + z * h, atol=1e-6)


@pytest.mark.parametrize("shape", [(8, 8), (3, 12), (12, 3)])
def test_orthogonal_init_is_orthogonal_and_batchable(shape):
    from pobax.memory import orthogonal

    w = orthogonal(jax.random.key(0), shape, scale=2.0)
    assert w.shape == shape
    small = min(shape)
    gram = w @ w.T if shape[0] <= shape[1] else w.T @ w
    np.testing.assert_allclose(gram, 4.0 * np.eye(small), atol=1e-5)
    # vmapped over seeds (model initialisation is): distinct draws, each orthogonal
    ws = jax.jit(jax.vmap(lambda k: orthogonal(k, shape)))(jax.random.split(jax.random.key(1), 3))
    assert not np.allclose(ws[0], ws[1])
    gram = ws[2] @ ws[2].T if shape[0] <= shape[1] else ws[2].T @ ws[2]
    np.testing.assert_allclose(gram, np.eye(small), atol=1e-5)


@pytest.mark.parametrize("shape", [(32, 32), (96, 32), (4, 64)])
def test_orthogonal_init_by_qr_equals_gram_schmidt(shape):
    """The GPU's QR decomposition and the CPU's Gram–Schmidt give the same matrix (Q with a positive diagonal
    of R is unique), so a seed initialises the same network on either platform. Unbatched: jaxlib's batched CPU
    QR is what can deadlock. "auto" is the choice of the platform the program is lowered for: the lowered program
    holds the QR's LAPACK/cuSOLVER call exactly where that platform's choice is "qr"."""
    import pobax.memory._layers as L
    from pobax._backend import orthogonal_method, platform_of

    out = {}
    for method in ("qr", "gram_schmidt"):
        out[method] = np.asarray(L.orthogonal(jax.random.key(3), shape, scale=1.5, method=method))
    np.testing.assert_allclose(out["qr"], out["gram_schmidt"], atol=2e-5)
    auto = jax.jit(lambda k: L.orthogonal(k, shape, scale=1.5))
    choice = orthogonal_method(platform_of())
    np.testing.assert_array_equal(np.asarray(auto(jax.random.key(3))), out[choice])
    hlo = auto.lower(jax.random.key(3)).as_text()
    assert ("geqrf" in hlo) == (choice == "qr")  # the QR's LAPACK (or cuSOLVER) call, only where it is the choice
    qr = jax.jit(lambda k: L.orthogonal(k, shape, method="qr")).lower(jax.random.key(3)).as_text()
    assert "geqrf" in qr  # what the test looks for is there when the QR is asked for


def test_gru_recurrent_product_as_reduce_equals_the_matmul():
    import pobax.memory._gru as G

    xs = jax.random.normal(jax.random.key(1), (12, 5))
    starts = jnp.zeros(12, bool).at[0].set(True).at[7].set(True)
    out = {}
    for impl in ("dot", "reduce"):
        gru = G.GRU(5, 16, key=jax.random.key(0), impl=impl)
        loss = lambda m: jnp.sum(m(m.init_carry(), xs, starts)[1] ** 2)  # noqa: E731
        out[impl] = (gru(gru.init_carry(), xs, starts)[1], jax.grad(loss)(gru).weight_hh)
    np.testing.assert_allclose(out["dot"][0], out["reduce"][0], atol=1e-5)
    np.testing.assert_allclose(out["dot"][1], out["reduce"][1], atol=1e-4)


@pytest.mark.slow
def test_recurrent_product_is_a_multiply_sum_only_up_to_the_grus_256_wide_weight():
    """On accelerators the multiply-sum is bounded by the weight's entries (3 × 256²): the LSTM at 256 wide (4 × 256²)
    stalled XLA's compile, the GRU at 256 is faster with it; the CPU never. The memories follow the `platform` they
    are built for, whatever platform builds them."""
    import pobax._backend as B
    from pobax.memory import GRU, LSTM

    assert [B.recurrent_product(w, "gpu") for w in (128, 256, 512)] == ["reduce", "reduce", "dot"]
    assert [B.recurrent_product(w, "gpu", gates=4) for w in (128, 221, 222, 256)] == ["reduce", "reduce", "dot", "dot"]
    key = jax.random.key(0)
    assert LSTM(3, 256, key=key, platform="gpu").impl == "dot"
    assert LSTM(3, 128, key=key, platform="gpu").impl == "reduce"
    assert LSTM(3, 32, key=key, platform="gpu").impl == GRU(3, 32, key=key, platform="gpu").impl == "fused"
    assert GRU(3, 256, key=key, platform="gpu").impl == "reduce"
    assert B.recurrent_product(32, "cpu") == B.recurrent_product(32, "cpu", gates=4) == B.lstm_impl(32, "cpu") == "dot"
    assert GRU(3, 32, key=key).impl == LSTM(3, 32, key=key).impl == "dot"  # the default platform: the CPU's


@pytest.mark.slow
def test_dense_as_multiply_sum_in_a_small_rollout_equals_the_matmul():
    """`with_matmul_batch`'s bound (2**22 on accelerators) makes one-row products a multiply and sum instead of a GEMM
    when the declared batch (the rollout's environments × runs) times the weight's entries is within it.
    Same values and gradients, vmapped over environments and seeds as in the rollout; sequences (the replay), an
    undeclared batch and a batch too large keep the GEMM."""
    import pobax.memory._gru as G
    import pobax.memory._layers as L

    gru = jax.vmap(lambda k: G.GRU(5, 16, key=k))(jax.random.split(jax.random.key(0), 2))  # 2 seeds
    xs = jax.random.normal(jax.random.key(1), (2, 3, 1, 5))  # seeds × environments × one time step
    starts = jnp.ones((2, 3, 1), bool)
    w = gru.pre.layers[0].weight[0]  # 16 × 5

    def step(m, x, s):
        return jax.vmap(lambda x, s: m(m.init_carry(), x, s)[1])(x, s)

    def loss(m):
        return jnp.sum(step(m, xs[0], starts[0]) ** 2)

    def primitives(x, batch, limit):
        return {str(e.primitive) for e in jax.make_jaxpr(lambda a, b: L.matmul_t(a, b, (batch, limit)))(x, w).jaxpr.eqns}

    out = {}
    big = 6 * 3 * 16 * 16  # 6 rows (2 seeds × 3 environments) × the largest weight, the input projection (3·16 × 16)
    for limit in (0, big):
        batched = L.with_matmul_batch(gru, 6, limit)
        assert batched.matmul_batch == batched.pre.layers[0].matmul_batch == (6, limit)
        assert gru.matmul_batch == gru.pre.layers[0].matmul_batch == L.NO_BATCH  # a copy: the original is unchanged
        out[limit] = (jax.jit(jax.vmap(step))(batched, xs, starts),
                      jax.grad(loss)(jax.tree.map(lambda a: a[0], batched)))
        assert ("reduce_sum" in primitives(xs[0, 0], 6, limit)) == (limit > 0)
        assert ("dot_general" in primitives(xs[0, 0], 6, limit)) == (limit == 0)
    np.testing.assert_allclose(out[0][0], out[big][0], atol=1e-5)
    for a, b in zip(jax.tree.leaves(out[0][1]), jax.tree.leaves(out[big][1])):
        np.testing.assert_allclose(a, b, atol=1e-4)
    assert "dot_general" in primitives(xs[0, :2, 0], 6, big)  # two rows: a sequence
    assert "dot_general" in primitives(xs[0, 0], 0, big)  # no declared batch
    assert "dot_general" in primitives(xs[0, 0], big // (16 * 5) + 1, big)  # rows × 16 × 5 above the bound
    from pobax._backend import rollout_reduce_limit

    assert "dot_general" in primitives(xs[0, 0], 6, rollout_reduce_limit("cpu"))  # the CPU's bound: a GEMM
    assert "reduce_sum" in primitives(xs[0, 0], 6, rollout_reduce_limit("gpu"))  # the GPU's: a multiply-sum


@pytest.mark.parametrize("impl", ["dot", "reduce"])
def test_gru_scan_manual_backward_equals_autodiff(impl):
    """The scan's hand-written backward (`SCAN_VJP="manual"`: weight gradient as one product after the loop) gives
    JAX's autodiff gradients for every input, through resets, vmapped over environments (shared weights) and over
    seeds (batched weights), with a non-trivial cotangent on both the outputs and the final carry."""
    from pobax.memory._gru import scan_recurrence

    S, B, T, H = 2, 3, 10, 6
    ks = jax.random.split(jax.random.key(0), 6)
    w = 0.5 * jax.random.normal(ks[0], (S, 3 * H, H))
    b = 0.3 * jax.random.normal(ks[1], (S, H))
    gx = jax.random.normal(ks[2], (S, B, T, 3 * H))
    starts = jax.random.bernoulli(ks[3], 0.25, (S, B, T)).at[:, :, 4].set(True)
    carry = jax.random.normal(ks[4], (S, B, H))
    wy = jax.random.normal(ks[5], (T, H))

    def loss(vjp, w, b, gx, carry):
        f = functools.partial(scan_recurrence, impl=impl, vjp=vjp, unroll=2)
        per_env = jax.vmap(f, in_axes=(None, None, 0, 0, 0))
        last, ys = jax.vmap(per_env)(w, b, gx, starts, carry)
        return jnp.sum(jnp.sin(last)) + jnp.sum(ys * wy[None, None])

    _assert_manual_equals_autodiff(loss, (w, b, gx, carry))
    with pytest.raises(ValueError, match="vjp must be"):
        scan_recurrence(w[0], b[0], gx[0, 0], starts[0, 0], carry[0, 0], vjp="numeric")


@pytest.mark.parametrize("impl", ["dot", "reduce"])
def test_lstm_manual_backward_equals_autodiff(impl):
    """The LSTM's hand-written backward gives JAX's autodiff gradients for the recurrent weights, the input
    projections and both parts of the incoming carry, through resets, vmapped over environments (shared weights)
    and seeds (batched weights), with cotangents on the outputs and on the final h and c; with the recurrent product
    as a matrix product or a multiply-sum (the accelerators' choice up to 256 wide), the autodiff of "dot" the
    reference for both."""
    from pobax.memory._lstm import lstm_recurrence

    S, B, T, H = 2, 3, 10, 5
    ks = jax.random.split(jax.random.key(1), 6)
    w = 0.5 * jax.random.normal(ks[0], (S, 4 * H, H))
    gx = jax.random.normal(ks[1], (S, B, T, 4 * H))
    starts = jax.random.bernoulli(ks[2], 0.25, (S, B, T)).at[:, :, 4].set(True).at[:, :, 0].set(False)
    h0, c0 = jax.random.normal(ks[3], (S, B, H)), jax.random.normal(ks[4], (S, B, H))
    wy = jax.random.normal(ks[5], (T, H))

    def loss(vjp, w, gx, h0, c0):
        f = functools.partial(lstm_recurrence, vjp=vjp, unroll=3, impl=impl if vjp == "manual" else "dot")
        h, c, ys = jax.vmap(jax.vmap(f, in_axes=(None, 0, 0, 0, 0)))(w, gx, starts, h0, c0)
        return jnp.sum(jnp.sin(h)) + jnp.sum(jnp.cos(c)) + jnp.sum(ys * wy[None, None])

    _assert_manual_equals_autodiff(loss, (w, gx, h0, c0))
    with pytest.raises(ValueError, match="vjp must be"):
        lstm_recurrence(w[0], gx[0, 0], starts[0, 0], h0[0, 0], c0[0, 0], vjp="numeric")
    with pytest.raises(ValueError, match="impl must be"):
        lstm_recurrence(w[0], gx[0, 0], starts[0, 0], h0[0, 0], c0[0, 0], impl="einsum")


def _assert_manual_equals_autodiff(loss, args):
    """`loss(vjp, *args)` and its gradients in every argument agree between the "manual" and "autodiff" VJPs, and
    every gradient is non-trivial."""
    grads = {v: jax.jit(jax.value_and_grad(functools.partial(loss, v), argnums=tuple(range(len(args)))))(*args)
             for v in ("manual", "autodiff")}
    np.testing.assert_allclose(grads["manual"][0], grads["autodiff"][0], rtol=1e-5)
    for gm, ga in zip(grads["manual"][1], grads["autodiff"][1]):
        assert float(jnp.max(jnp.abs(ga))) > 1e-3
        np.testing.assert_allclose(gm, ga, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("shape", [(32, 3, 7, 7), (96, 32), (5,)])
def test_flat_draws_equal_shaped_draws_inside_and_outside_a_program(shape):
    """`flat_draw` gives the values of the shaped draw (it only spares XLA's CPU compiler a draw over several axes),
    eagerly, jitted and vmapped over keys, so pobax's initialisers draw what they drew as shaped draws."""
    from pobax.memory import flat_draw

    for sample in (jax.random.uniform, jax.random.normal):
        key = jax.random.key(11)
        shaped, flat = sample(key, shape), flat_draw(sample, key, shape)
        assert flat.shape == shape and np.array_equal(shaped, flat)
        keys = jax.random.split(key, 3)
        kwargs = {"minval": -0.5} if sample is jax.random.uniform else {}
        batched = lambda draw: jax.jit(jax.vmap(draw))(keys)  # noqa: E731
        np.testing.assert_array_equal(batched(lambda k: sample(k, shape, **kwargs)),
                                      batched(lambda k: flat_draw(sample, k, shape, **kwargs)))
