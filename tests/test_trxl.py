"""Transformer-XL memory: chunking invariance, episode isolation, the sliding window, truncated gradients."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

from pobax.memory import TransformerXL, TrXLCarry

IN, EMBED, MEM, GRAD = 3, 16, 5, 4
T = 27  # one sequence length almost everywhere, so that compiled programs are reused across tests


@functools.cache
def small(num_layers: int = 2, **kw) -> TransformerXL:
    return TransformerXL(
        IN,
        key=jax.random.key(0),
        embed_size=EMBED,
        num_heads=2,
        num_layers=num_layers,
        qkv_features=8,
        window_mem=MEM,
        window_grad=GRAD,
        **kw,
    )


@functools.cache
def trained(num_layers: int = 2) -> TransformerXL:
    """A small model with every parameter moved off its initial value, as after training.

    At initialisation LayerNorms are (1, 0), attention biases 0, and so on: symmetries that could hide a bug
    (e.g. cached and current steps normalised by different parameters).
    """
    model = small(num_layers)
    leaves, treedef = jax.tree.flatten(model)
    rng = np.random.default_rng(42)  # numpy: no per-shape compilation for a one-off perturbation
    leaves = [
        jnp.asarray(np.asarray(leaf) + 0.3 * rng.standard_normal(leaf.shape, np.float32)) for leaf in leaves
    ]
    return jax.tree.unflatten(treedef, leaves)


def data(time: int = T, seed: int = 1, starts_at=(0, 9, 10, 17)):
    xs = jax.random.normal(jax.random.key(seed), (time, IN))
    starts = jnp.zeros((time,), bool).at[jnp.array(starts_at)].set(True)
    return xs, starts


@eqx.filter_jit
def run(model, carry, xs, starts):
    return model(carry, xs, starts)


def run_chunked(model, carry, xs, starts, sizes):
    outs, t = [], 0
    for n in sizes:
        carry, ys = run(model, carry, xs[t : t + n], starts[t : t + n])
        outs.append(ys)
        t += n
    assert t == xs.shape[0]
    return carry, jnp.concatenate(outs)


def test_stepping_equals_one_call_with_resets_and_cache_rollover():
    # 27 steps: several windows of 4 plus a remainder, episodes longer and shorter than window_mem (5), and two
    # starts in a row (a one-step episode). Chunks of 5 = one window of 4 + a remainder of 1.
    model, (xs, starts) = trained(), data()
    carry0 = model.init_carry()
    carry_all, ys_all = run(model, carry0, xs, starts)
    for sizes in ([1] * T, [5] * 5 + [1, 1]):
        carry, ys = run_chunked(model, carry0, xs, starts, sizes)
        np.testing.assert_allclose(ys, ys_all, atol=1e-5, rtol=1e-5)
        np.testing.assert_allclose(carry.memory, carry_all.memory, atol=1e-5, rtol=1e-5)
        np.testing.assert_array_equal(carry.valid, carry_all.valid)
    # The last episode started at step 17, so all 5 cached steps (22..26) are in it.
    assert carry_all.valid.all()


def test_carry_validity_tracks_the_current_episode():
    model = trained()
    xs, starts = data(starts_at=(0, 25))
    carry, _ = run(model, model.init_carry(), xs, starts)
    # Cache holds steps 22..26 (oldest first); only 25 and 26 belong to the episode that started at 25.
    np.testing.assert_array_equal(carry.valid, [False, False, False, True, True])


def test_a_new_episode_never_sees_the_previous_one():
    model, (xs, starts) = trained(), data()
    carry0 = model.init_carry()
    _, ys = run(model, carry0, xs, starts)
    # Perturb everything before the start at step 17: outputs from 17 on are bitwise unchanged.
    xs_perturbed = xs.at[:17].add(jax.random.normal(jax.random.key(7), (17, IN)) * 10.0)
    _, ys_perturbed = run(model, carry0, xs_perturbed, starts)
    np.testing.assert_array_equal(ys_perturbed[17:], ys[17:])
    assert not np.allclose(ys_perturbed[:17], ys[:17])  # the perturbation did matter where it may


def test_a_start_ignores_whatever_is_in_the_cache():
    model, (xs, starts) = trained(), data()
    # A cache full of (valid-flagged) garbage from an earlier call: a start at step 0 must wipe it.
    garbage = TrXLCarry(
        memory=jax.random.normal(jax.random.key(3), (2, MEM, EMBED)) * 5.0, valid=jnp.ones((MEM,), bool)
    )
    _, ys_clean = run(model, model.init_carry(), xs, starts)
    _, ys_garbage = run(model, garbage, xs, starts)
    np.testing.assert_array_equal(ys_garbage, ys_clean)
    # Without the start, the cache is used.
    _, ys_continued = run(model, garbage, xs, starts.at[0].set(False))
    assert not np.allclose(ys_continued[0], ys_clean[0])


def test_context_is_window_mem_steps_per_layer():
    # One layer sees the window_mem previous inputs; each extra layer reaches window_mem further back.
    num_layers = 2
    model = trained(num_layers)
    xs, starts = data(starts_at=(0,))
    t = T - 1
    reach = num_layers * MEM
    _, ys = run(model, model.init_carry(), xs, starts)
    _, ys_far = run(model, model.init_carry(), xs.at[t - reach - 1].add(10.0), starts)
    _, ys_near = run(model, model.init_carry(), xs.at[t - reach].add(10.0), starts)
    np.testing.assert_array_equal(ys_far[t], ys[t])
    assert not np.allclose(ys_near[t], ys[t])


def test_gradients_stay_inside_a_window_and_never_reach_the_carry():
    model, (xs, starts) = trained(), data(starts_at=(0,))
    carry = TrXLCarry(
        memory=jax.random.normal(jax.random.key(4), (2, MEM, EMBED)), valid=jnp.ones((MEM,), bool)
    )

    def last_output(memory, xs):
        return model(TrXLCarry(memory=memory, valid=carry.valid), xs, starts)[1][-1].sum()

    g_memory, g_xs = jax.jit(jax.grad(last_output, argnums=(0, 1)))(carry.memory, xs)
    assert not np.any(g_memory)
    # 27 steps = windows 0..3, ..., 20..23 and a last one 24..26: the last output's gradient reaches inputs
    # 24..26 only, although its value does depend on step 23 (through the cache).
    assert np.all(np.abs(g_xs[24:]).sum(-1) > 0)
    assert not np.any(g_xs[:24])
    _, ys = run(model, carry, xs, starts)
    _, ys_perturbed = run(model, carry, xs.at[23].add(1.0), starts)
    assert not np.allclose(ys_perturbed[-1], ys[-1])


def test_jit_and_vmap_over_a_batch():
    model = trained()
    batch = 3
    xs = jax.random.normal(jax.random.key(5), (batch, T, IN))
    starts = jnp.zeros((batch, T), bool).at[:, 0].set(True).at[1, 4].set(True)
    carries = jax.vmap(lambda _: model.init_carry())(jnp.arange(batch))
    out_carry, ys = eqx.filter_jit(eqx.filter_vmap(model))(carries, xs, starts)
    assert ys.shape == (batch, T, EMBED) and out_carry.memory.shape == (batch, 2, MEM, EMBED)
    for b in range(batch):
        _, ys_b = run(model, model.init_carry(), xs[b], starts[b])
        np.testing.assert_allclose(ys[b], ys_b, atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_gating_bias_starts_blocks_near_identity():
    xs, starts = data()
    for gating_bias, close in ((30.0, True), (0.0, False)):
        model = small(gating_bias=gating_bias)
        _, ys = run(model, model.init_carry(), xs, starts)
        assert np.allclose(ys, jax.vmap(model.encoder)(xs), atol=1e-5) == close
    ungated = small(gating=False)  # plain residual connections
    assert ungated.blocks[0].gate_attn is None
    # Tracing (not compiling) is enough to show the ungated path is well-formed.
    assert eqx.filter_eval_shape(ungated, ungated.init_carry(), xs, starts)[1].shape == (T, EMBED)


def test_shapes_are_checked():
    model = small()
    xs, starts = data(6)
    with pytest.raises(ValueError, match=r"in_size=3\): xs must be an array of shape \(time >= 1, 3\), got \(6, 4\)"):
        model(model.init_carry(), jnp.zeros((6, IN + 1)), starts)
    with pytest.raises(jaxtyping.TypeCheckError):
        model(model.init_carry(), xs, starts[:5])
    with pytest.raises(jaxtyping.TypeCheckError):  # window_mem disagrees between the carry's fields
        TrXLCarry(memory=jnp.zeros((2, MEM, EMBED)), valid=jnp.zeros((MEM - 1,), bool))


def test_defaults_follow_the_paper():
    model = eqx.filter_eval_shape(TransformerXL, 4, key=jax.random.key(0))  # shapes only: no 256x256 QRs
    assert (model.in_size, model.out_size, model.num_layers) == (4, 256, 2)
    assert (model.window_mem, model.window_grad) == (128, 64)
    block = model.blocks[0]
    assert block.num_heads == 8 and block.query.weight.shape == (256, 256)
    assert block.gate_attn is not None
    # The default gating_bias (2.0) is the negated initial z-bias of both gates.
    gate = small().blocks[0].gate_ff
    np.testing.assert_array_equal(gate.from_y.bias[EMBED : 2 * EMBED], -2.0)
    np.testing.assert_array_equal(gate.from_y.bias[:EMBED], 0.0)


def test_check_window():
    TransformerXL.check_window(128, 64)
    with pytest.raises(ValueError, match=r"num_steps \(100\) must be a multiple of window_grad \(64\)"):
        TransformerXL.check_window(100, 64)
    with pytest.raises(ValueError, match="multiple of num_heads"):
        TransformerXL(IN, key=jax.random.key(0), num_heads=3, qkv_features=8)


# --- Absorbed attention (the cheap rollout step) equals the textbook projected form -----------------------


def with_attention(model: TransformerXL, attention: str) -> TransformerXL:
    """The same parameters, computed with `attention` ("projected" is the original computation, kept as the
    reference: every key, value and relative position of [cache; window] projected at every call)."""
    like = TransformerXL(
        model.in_size, key=jax.random.key(0), embed_size=model.out_size,
        num_heads=model.blocks[0].num_heads, num_layers=model.num_layers,
        qkv_features=model.blocks[0].query.weight.shape[0], window_mem=model.window_mem,
        window_grad=model.window_grad, gating=model.blocks[0].gate_attn is not None, attention=attention,
    )
    return jax.tree.unflatten(jax.tree.structure(like), jax.tree.leaves(model))


@functools.cache
def narrow() -> TransformerXL:
    """T-Maze's shape in small: embed (6) smaller than head_dim (8), where absorbing pays off most."""
    model = TransformerXL(IN, key=jax.random.key(1), embed_size=6, num_heads=2, num_layers=2, qkv_features=16,
                          window_mem=MEM, window_grad=GRAD)
    rng = np.random.default_rng(43)
    leaves, treedef = jax.tree.flatten(model)
    return jax.tree.unflatten(treedef, [jnp.asarray(np.asarray(x) + 0.3 * rng.standard_normal(x.shape, np.float32))
                                        for x in leaves])


@pytest.mark.slow
@pytest.mark.parametrize("which", ["trained", pytest.param("narrow", marks=pytest.mark.slow)])
def test_absorbed_attention_equals_projected_stepping_and_replay(which):
    model = trained() if which == "trained" else narrow()
    reference, absorbed = with_attention(model, "projected"), with_attention(model, "absorbed")
    assert model.attention == "auto" and reference.attention == "projected"
    # Random inputs, episode starts mid-sequence (and one right after another), a cache full of garbage flagged
    # valid from an "earlier call" (used until the first start, since the sequence does not begin with one).
    xs, starts = data(seed=11, starts_at=(6, 13, 14, 21))
    carry0 = TrXLCarry(
        memory=jax.random.normal(jax.random.key(12), (2, MEM, model.out_size)), valid=jnp.ones((MEM,), bool)
    )
    carry_ref, ys_ref = run(reference, carry0, xs, starts)
    for candidate in (absorbed, model):  # forced, and "auto" (absorbed steps, projected or absorbed windows)
        for sizes in ([T], [1] * T, [5] * 5 + [1, 1]):  # replay in one call; rollout; mixed
            carry, ys = run_chunked(candidate, carry0, xs, starts, sizes)
            np.testing.assert_allclose(ys, ys_ref, atol=1e-5, rtol=1e-5)
            np.testing.assert_allclose(carry.memory, carry_ref.memory, atol=1e-5, rtol=1e-5)
            np.testing.assert_array_equal(carry.valid, carry_ref.valid)
    # The garbage mattered before the first start, and the carry layout is unchanged.
    _, ys_clean = run(reference, reference.init_carry(), xs, starts)
    assert not np.allclose(ys_ref[:6], ys_clean[:6])
    np.testing.assert_array_equal(ys_ref[6:], ys_clean[6:])
    assert jax.tree.structure(carry0) == jax.tree.structure(absorbed.init_carry())


@pytest.mark.slow
def test_absorbed_attention_has_the_same_gradients():
    # The PPO update replays whole segments: its gradients (parameters and inputs; none into the carry) agree.
    model = narrow()
    xs, starts = data(seed=13, starts_at=(3, 17))
    carry = TrXLCarry(memory=jax.random.normal(jax.random.key(14), (2, MEM, 6)), valid=jnp.ones((MEM,), bool))

    @eqx.filter_jit
    @eqx.filter_grad
    def grads(model_xs_carry):
        m, x, c = model_xs_carry
        return jnp.sum(jnp.sin(m(c, x, starts)[1]))

    g_ref = grads((with_attention(model, "projected"), xs, carry))
    g_abs = grads((with_attention(model, "absorbed"), xs, carry))
    for a, b in zip(jax.tree.leaves(g_ref), jax.tree.leaves(g_abs), strict=True):
        np.testing.assert_allclose(b, a, atol=1e-4, rtol=1e-4)
    assert not np.any(g_abs[2].memory)  # still no gradient into the saved cache


def test_auto_attention_absorbs_every_step_and_small_embeddings():
    tmaze = eqx.filter_eval_shape(TransformerXL, 4, key=jax.random.key(0), embed_size=12)  # T-Maze's sizes
    default = eqx.filter_eval_shape(TransformerXL, 4, key=jax.random.key(0))  # embed 256
    for model in (tmaze, default):
        assert model.blocks[0].absorbs(1, 128 + 1)  # one rollout step against a full cache
    assert tmaze.blocks[0].absorbs(64, 128 + 64)  # replay windows too, when embed (12) << head_dim (32)
    assert not default.blocks[0].absorbs(64, 128 + 64)  # but not with embed 256: project once per window
    with pytest.raises(ValueError, match="attention must be"):
        TransformerXL(IN, key=jax.random.key(0), attention="cached")
