import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax.agent import Flatten, FullImageCNN, SmallImageCNN, make_encoder


@pytest.mark.parametrize("shape, cls", [((2, 3, 2), SmallImageCNN), ((2, 3, 5), SmallImageCNN),
                                        ((32, 32, 3), FullImageCNN), ((27, 33, 3), FullImageCNN), ((7,), Flatten)])
def test_encoders_pick_by_size_and_produce_hidden_features(shape, cls):
    enc = make_encoder(shape, 16, key=jax.random.key(0))
    assert isinstance(enc, cls)
    y = enc(jnp.ones(shape))
    assert y.shape == ((16,) if cls is not Flatten else (7,))
    assert np.isfinite(y).all()


def test_uint8_images_are_scaled_to_unit_range():
    enc = FullImageCNN((32, 32, 3), 8, key=jax.random.key(0))
    img = jax.random.randint(jax.random.key(1), (32, 32, 3), 0, 256).astype(jnp.uint8)
    np.testing.assert_allclose(enc(img), enc(img.astype(jnp.float32) / 255.0), atol=1e-5)


def test_encoder_option_forces_a_kind_and_rejects_cnns_for_vectors():
    assert isinstance(make_encoder((21, 41, 6), 16, key=jax.random.key(0), kind="flatten"), Flatten)
    assert isinstance(make_encoder((2, 3, 2), 16, key=jax.random.key(0), kind="full_cnn"), FullImageCNN)
    img = jax.random.randint(jax.random.key(1), (4, 4, 3), 0, 256).astype(jnp.uint8)
    flat = make_encoder((4, 4, 3), 16, key=jax.random.key(0), kind="flatten")
    np.testing.assert_allclose(flat(img), np.asarray(img, np.float32).reshape(-1) / 255.0, rtol=1e-6)
    with pytest.raises(ValueError, match="needs image observations"):
        make_encoder((7,), 16, key=jax.random.key(0), kind="small_cnn")
    assert isinstance(make_encoder((20, 20, 3), 16, key=jax.random.key(0), kind="small_cnn"), SmallImageCNN)
    with pytest.raises(ValueError, match="at most 20 px a side .* got 37x61"):
        make_encoder((37, 61, 6), 16, key=jax.random.key(0), kind="small_cnn")


def test_train_config_encoder_reaches_the_network():
    from pobax.agent import TrainConfig
    from pobax.agent._ppo import make_model
    from pobax.env import make

    cfg = TrainConfig(env="Navix-DMLab-Maze-01-v0", observability="full", memory="memoryless", encoder="flatten",
                      hidden_size=8)
    model = make_model(cfg, make(cfg.env, cfg.observability), jax.random.key(0))
    assert isinstance(model.encoder, Flatten) and model.encoder.out_size == 21 * 41 * 6


def test_egocentric_turns_the_map_to_the_heading_and_checks_its_input():
    """A 3x5 map with one marked cell east of the centre: whatever the heading channel says, the mark lands where that
    heading's "ahead", "left" or "behind" is once turned to point up (MiniGrid: 0 east, 1 south, 2 west, 3 north)."""
    from pobax.agent import Egocentric

    enc = make_encoder((3, 5, 5), 16, key=jax.random.key(0), kind="egocentric")
    assert isinstance(enc, Egocentric) and enc.out_size == 5 * 5 * 1
    mark = np.zeros((3, 5, 1), np.float32)
    mark[1, 3, 0] = 1.0  # one cell east of the centre (1, 2)
    where = {}
    for heading in range(4):
        obs = np.concatenate([mark, np.broadcast_to(np.eye(4)[heading], (3, 5, 4))], axis=-1)
        out = np.asarray(enc(jnp.asarray(obs))).reshape(5, 5)
        assert out.sum() == 1.0
        where[heading] = tuple(int(i) for i in np.argwhere(out)[0])
    # centre of the 5x5 square is (2, 2); "up" is row 1
    assert where == {0: (1, 2), 1: (2, 1), 2: (3, 2), 3: (2, 3)}  # east mark: ahead, left, behind, right
    for bad in [(4, 5, 6), (3, 5, 4)]:
        with pytest.raises(ValueError, match="egocentric"):
            make_encoder(bad, 16, key=jax.random.key(0), kind="egocentric")



def test_mlp_encoder_is_three_relu_layers_on_the_flattened_observation():
    from pobax.agent import MLPEncoder, TrainConfig
    from pobax.agent._ppo import make_model
    from pobax.env import make

    enc = make_encoder((2, 3), 8, key=jax.random.key(0), kind="mlp")
    assert isinstance(enc, MLPEncoder) and enc.out_size == 8
    assert [layer.weight.shape for layer in enc.mlp.layers] == [(8, 6), (8, 8), (8, 8)]
    x = jax.random.normal(jax.random.key(1), (2, 3))
    h = x.reshape(-1)
    for layer in enc.mlp.layers:
        h = jnp.maximum(layer.weight @ h + layer.bias, 0.0)
    np.testing.assert_allclose(enc(x), h, rtol=1e-5, atol=1e-6)
    # before a GRU: with the GRU's own Dense, four Dense layers from the observation (with the previous action) on
    cfg = TrainConfig(env="rocksample_11_11", memory="gru", encoder="mlp", hidden_size=16, action_concat=True)
    model = make_model(cfg, make(cfg.env, action_concat=True), jax.random.key(0))
    assert isinstance(model.encoder, MLPEncoder) and model.encoder.mlp.layers[0].weight.shape == (16, 33 + 16)
    with pytest.raises(ValueError, match="choose auto, flatten, small_cnn, full_cnn, egocentric or mlp"):
        make_encoder((7,), 16, key=jax.random.key(0), kind="mlp4")


def test_release_init_has_the_original_releases_gains_and_starts_blind():
    """`init="release"`: the per-layer spread the original release's saved parameters show (docs/parity.md), the same
    orthogonal draws as pobax's, and features that start near zero: the actor's logits hardly depend on the input."""
    from pobax.agent import ConfigError, TrainConfig, config_from_dict, validate
    from pobax.agent._ppo import make_model
    from pobax.env import make

    h = 64
    env = make("rocksample_11_11", action_concat=True)
    cfg = TrainConfig(env="rocksample_11_11", memory="gru", encoder="mlp", hidden_size=h, action_concat=True)
    ppo = make_model(cfg, env, jax.random.key(0))
    rel = make_model(dataclasses.replace(cfg, init="release"), env, jax.random.key(0))
    dense = lambda m: [*m.encoder.mlp.layers, *m.memory.pre.layers, m.actor.hidden, m.critics[0].hidden]  # noqa: E731
    for a, b, gain in zip(dense(ppo), dense(rel), [2.0, 0.01, 0.01, 0.01, 2.0, 2.0]):
        np.testing.assert_allclose(b.weight, a.weight * gain / np.sqrt(2.0), rtol=1e-6)  # the same draw, rescaled
        rows, cols = b.weight.shape
        assert np.std(np.asarray(b.weight)) == pytest.approx(gain / np.sqrt(max(rows, cols)), rel=0.02)
    assert np.std(np.asarray(rel.memory.weight_ih)) == pytest.approx(1 / np.sqrt(h), rel=0.05)
    np.testing.assert_array_equal(rel.actor.out.weight, ppo.actor.out.weight)  # outputs untouched
    np.testing.assert_array_equal(rel.memory.weight_hh, ppo.memory.weight_hh)
    # ReLU layers without bias scale with their gains: the GRU's input is 2·0.01³/√2⁴ = 5e-7 of pobax's (blind)
    obs = jax.random.uniform(jax.random.key(1), (2, 33 + 16))
    feats = lambda m: jax.nn.relu(m.memory.pre(jax.vmap(m.encoder)(obs)))  # noqa: E731
    np.testing.assert_allclose(feats(rel), 5e-7 * feats(ppo), rtol=1e-3, atol=1e-12)
    with pytest.raises(ConfigError, match="--init must be one of ppo, release"):  # as config.json or a preset gives it
        config_from_dict({"env": "rocksample_11_11", "init": "xavier"})
    for memory, encoder in (("trxl", "auto"), ("lstm", "auto"), ("gru", "small_cnn")):
        with pytest.raises(ConfigError, match="--init release"):
            validate(TrainConfig(env="rocksample_11_11", memory=memory, encoder=encoder, init="release"))


@pytest.mark.slow
def test_release_init_keeps_a_continuous_actors_hidden_gain():
    """The release's continuous agents (Walker-V) keep gain √2 on the actor's hidden layer; the critic's is 2."""
    from pobax.agent import TrainConfig
    from pobax.agent._ppo import make_model
    from pobax.env import make

    env = make("Walker-V-v0")
    cfg = TrainConfig(env="Walker-V-v0", memory="gru", hidden_size=32)
    ppo = make_model(cfg, env, jax.random.key(0))
    rel = make_model(dataclasses.replace(cfg, init="release"), env, jax.random.key(0))
    np.testing.assert_array_equal(rel.actor.hidden.weight, ppo.actor.hidden.weight)
    np.testing.assert_allclose(rel.critics[0].hidden.weight, ppo.critics[0].hidden.weight * np.sqrt(2.0), rtol=1e-6)
    np.testing.assert_allclose(rel.memory.pre.layers[0].weight, ppo.memory.pre.layers[0].weight * np.sqrt(2.0),
                               rtol=1e-6)


@pytest.mark.parametrize("cin,cout,kernel,stride", [(3, 32, 7, 4), (32, 32, 3, 2), (2, 8, 2, 1)])
def test_conv2d_is_equinox_conv2d_with_the_same_initial_weights(cin, cout, kernel, stride):
    """The CNNs' convolutions (`conv2d`, drawn flat) are Equinox's `Conv2d` with SAME padding and its default
    initialisation, value for value: same leaves, same outputs."""
    import equinox as eqx

    from pobax.agent._encoders import conv2d

    key = jax.random.key(cin + kernel)
    ours = conv2d(cin, cout, kernel, stride=stride, key=key)
    theirs = eqx.nn.Conv2d(cin, cout, kernel, stride=stride, padding="SAME", key=key)
    assert bool(eqx.tree_equal(ours, theirs))  # same structure, statics and array values
    x = jax.random.normal(jax.random.key(2), (cin, 12, 12))
    np.testing.assert_array_equal(ours(x), theirs(x))
