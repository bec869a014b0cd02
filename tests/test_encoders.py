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
