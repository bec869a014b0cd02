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


def test_train_config_encoder_reaches_the_network():
    from pobax.agent import TrainConfig
    from pobax.agent._ppo import make_model
    from pobax.env import make

    cfg = TrainConfig(env="Navix-DMLab-Maze-01-v0", observability="full", memory="memoryless", encoder="flatten",
                      hidden_size=8)
    model = make_model(cfg, make(cfg.env, cfg.observability), jax.random.key(0))
    assert isinstance(model.encoder, Flatten) and model.encoder.out_size == 21 * 41 * 6
