"""Implementation choices are configuration: `pobax._backend.Backend`, resolved by `Runs` from the devices it trains
on (and `TrainConfig.backend`'s overrides), reaches the network and the environment as fields, whatever platform
builds them. Asking for the GPU's choices here, on the CPU, builds what a GPU would run."""

import dataclasses

import equinox as eqx
import jax
import numpy as np
import pytest

import pobax._backend as B
from pobax.agent import ConfigError, Runs, TrainConfig
from pobax.agent._network import memory_options
from pobax.agent._ppo import make_model
from pobax.env import AutoReset, make
from pobax.env._wrappers import for_backend
from pobax.memory import GRU, LSTM

TINY = dict(hidden_size=8, num_envs=2, num_minibatches=2, num_steps=8, total_steps=2 * 8 * 2, num_seeds=1,
            num_chunks=1)


def _wrappers(env):
    while True:
        yield env
        if not hasattr(env, "env"):
            return
        env = env.env


def test_the_platforms_choices_and_overrides():
    gpu, cpu = B.Backend("gpu"), B.Backend("cpu")
    assert (gpu.gru(32), gpu.gru(128), gpu.gru(512)) == ("fused", "reduce", "dot")
    assert (gpu.lstm(32), gpu.lstm(128), gpu.lstm(256)) == ("fused", "reduce", "dot")
    assert (cpu.gru(32), cpu.lstm(32)) == ("dot", "dot")
    assert (gpu.scan_unroll(), gpu.reduce_limit(), gpu.pool_size(), gpu.loop_free()) == (4, 2**22, None, True)
    assert (cpu.scan_unroll(), cpu.reduce_limit(), cpu.pool_size(), cpu.loop_free()) == (1, 0, 8, False)
    assert (gpu.gae(), cpu.gae()) == ("auto", "auto")
    over = B.Backend.of(None, "gru_impl=dot,rollout_reduce_limit=0,reset_pool_size=none,loop_free_placements=true,"
                              "gae_method=sequential")
    assert over.platform == B.platform_of() == jax.devices()[0].platform
    assert (over.gru(32), over.reduce_limit(), over.pool_size(), over.loop_free(), over.gae()) == \
        ("dot", 0, None, True, "sequential")
    assert over.lstm(32) == B.lstm_impl(32, over.platform)  # not overridden: the platform's
    for bad in ("gru_impl=einsum", "unroll=0", "nonsense=1", "gru_impl", "reset_pool_size=0", "gae_method=fast"):
        with pytest.raises(ValueError, match="Bad backend choice"):
            B.parse_overrides(bad)
    hash(over)  # part of a compiled program's static configuration


@pytest.mark.slow
def test_the_gpus_network_is_built_on_the_cpu_when_asked_for():
    """The network follows its backend, not the platform that builds it: asked for the GPU's choices, the CPU builds
    the GPU's fused GRU and LSTM for the GPU (Triton kernels), their loops unrolled 4."""
    env = make("tmaze_3")
    for memory, cls in (("gru", GRU), ("lstm", LSTM)):
        cfg = TrainConfig(env="tmaze_3", memory=memory, hidden_size=8)
        model = make_model(cfg, env, jax.random.key(0), B.Backend("gpu"))
        assert isinstance(model.memory, cls)
        assert (model.memory.impl, model.memory.platform, model.memory.unroll) == ("fused", "gpu", 4)
        assert memory_options(cfg, B.Backend("gpu")) == {**memory_options(cfg), "impl": "fused", "platform": "gpu",
                                                         "unroll": 4}
        model = make_model(cfg, env, jax.random.key(0))  # the default: the CPU's
        assert (model.memory.impl, model.memory.platform, model.memory.unroll) == ("dot", "cpu", 1)
        explicit = make_model(dataclasses.replace(cfg, unroll=3), env, jax.random.key(0), B.Backend("gpu"))
        assert explicit.memory.unroll == 3  # the configuration's unroll wins over the platform's


def test_the_fused_gru_the_gpu_would_choose_runs_here_in_the_interpreter():
    """The GPU's choice for a 16-wide GRU, built for the CPU: the same function (Pallas' interpreter) as the scan."""
    xs = jax.random.normal(jax.random.key(1), (8, 5))
    starts = jax.numpy.zeros(8, bool).at[0].set(True).at[5].set(True)
    fused = GRU(5, 16, key=jax.random.key(0), impl=B.gru_impl(16, "gpu"), platform="cpu")
    scan = GRU(5, 16, key=jax.random.key(0))
    assert (fused.impl, scan.impl) == ("fused", "dot")
    ys_fused, ys_scan = (m(m.init_carry(), xs, starts)[1] for m in (fused, scan))
    np.testing.assert_allclose(ys_fused, ys_scan, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["battleship_10", "rocksample_5_5"])
def test_the_environment_takes_the_backends_reset_choices_and_plays_the_same_episodes(name):
    env = make(name)
    pooled = [w for w in _wrappers(env) if isinstance(w, AutoReset)]
    assert pooled and pooled[0].pool_by_platform and pooled[0].pool_size == 8  # unconfigured: the CPU's
    on_gpu = for_backend(env, B.Backend("gpu"))
    assert [w.pool_size for w in _wrappers(on_gpu) if isinstance(w, AutoReset)] == [None]
    loop_free = [w.loop_free for w in _wrappers(on_gpu) if hasattr(w, "loop_free")]
    assert loop_free == ([True] if name.startswith("battleship") else [])
    assert env.observation_space == on_gpu.observation_space

    def play(e, n=4, steps=40):
        keys = jax.random.split(jax.random.key(0), n)
        state, ts = jax.vmap(lambda k: e.reset(key=k))(keys)

        def step(carry, k):
            state, _ = carry
            acts = jax.vmap(lambda kk: e.action_space.sample(kk))(jax.random.split(k, n))
            state, ts = jax.vmap(lambda s, a, kk: e.step(s, a, key=kk))(state, acts, jax.random.split(k, n))
            return (state, ts.reward), (ts.reward, ts.done)

        return jax.jit(lambda: jax.lax.scan(step, (state, ts.reward), jax.random.split(jax.random.key(1), steps))[1])()

    for a, b in zip(jax.tree.leaves(play(env)), jax.tree.leaves(play(on_gpu))):
        np.testing.assert_array_equal(a, b)


def test_runs_resolve_the_backend_from_their_devices_and_the_configuration():
    runs = Runs(TrainConfig(env="tmaze_3", memory="gru", **TINY))
    assert runs.backend == B.Backend(B.platform_of(jax.devices()))
    assert runs.init().model.memory.impl == B.gru_impl(8, runs.backend.platform)
    runs = Runs(TrainConfig(env="tmaze_3", memory="gru", backend="gru_impl=reduce,unroll=2", **TINY))
    model = runs.init().model
    assert (model.memory.impl, model.memory.unroll) == ("reduce", 2)
    assert runs.fixed(0)[1] is runs.backend  # the chunk program's static configuration
    with pytest.raises(ConfigError, match="--backend: Bad backend choice 'gru_impl=einsum'"):
        Runs(TrainConfig(env="tmaze_3", memory="gru", backend="gru_impl=einsum", **TINY))


@pytest.mark.slow
def test_a_variant_trains_the_same_runs_up_to_rounding(monkeypatch):
    """The GPU's layer choices asked for on the CPU (multiply-sum GRU loop and rollout layers), and GAE as a
    sequential scan (its "auto" is the weighted sum at 8 steps): the same training, float rounding aside."""
    import pobax.agent._ppo as ppo

    methods, gae = [], ppo.gae
    monkeypatch.setattr(ppo, "gae", lambda *a, method: methods.append(method) or gae(*a, method=method))
    cfg = TrainConfig(env="tmaze_3", memory="gru", fast_compile=True, **TINY)
    plain, variant = Runs(cfg), Runs(dataclasses.replace(
        cfg, backend="gru_impl=reduce,rollout_reduce_limit=4194304,gae_method=sequential"))
    states = []
    for runs in (plain, variant):
        chunk = next(runs.chunks(runs.init()))
        states.append(eqx.filter(chunk.state.model, eqx.is_array))
    assert methods == ["auto", "sequential"]  # the update was traced once with each
    for a, b in zip(jax.tree.leaves(states[0]), jax.tree.leaves(states[1])):
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_runs_configure_an_environment_they_are_given():
    """An environment passed to `Runs` (a wrapped one, say) is configured for the backend as a registered one is."""
    cfg = TrainConfig(env="rocksample_5_5", memory="memoryless", backend="reset_pool_size=3", **TINY)
    runs = Runs(cfg, env=make("rocksample_5_5"))
    assert [w.pool_size for w in _wrappers(runs.env) if isinstance(w, AutoReset)] == [3]
