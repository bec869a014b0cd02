import jax
import jax.numpy as jnp
import pytest

from pobax.agent import enable_compile_cache


@pytest.fixture
def restore_cache_config():
    from jax._src import compilation_cache

    before = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    yield
    jax.config.update("jax_compilation_cache_dir", before[0])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])
    compilation_cache.reset_cache()


def test_compile_cache_off_and_cpu_default(monkeypatch, restore_cache_config):
    monkeypatch.setenv("POBAX_COMPILE_CACHE", "off")
    assert enable_compile_cache() is None
    monkeypatch.delenv("POBAX_COMPILE_CACHE")
    if jax.config.jax_compilation_cache_dir is None and jax.default_backend() == "cpu":
        assert enable_compile_cache(accelerators_only=True) is None  # the CLI's default on CPU
        assert jax.config.jax_compilation_cache_dir is None


def test_compile_cache_writes_executables(tmp_path, monkeypatch, restore_cache_config):
    from jax._src import compilation_cache

    monkeypatch.setenv("POBAX_COMPILE_CACHE", "off")  # a path given wins over the variable
    jax.config.update("jax_compilation_cache_dir", None)
    compilation_cache.reset_cache()
    assert enable_compile_cache(tmp_path / "xla") == tmp_path / "xla"
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)(jnp.arange(7.0)).block_until_ready()
    assert any((tmp_path / "xla").iterdir())
