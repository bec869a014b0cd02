import dataclasses
import tempfile
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pobax.env as E
from pobax.agent import Categorical, DiagGaussian, Hyperparams, TrainConfig, init_state, train, update
from pobax.agent import _train


class ConstantReward(E.AbstractEnvironment):
    """Reward 1 every step, a constant observation, never terminates: V = 1 / (1 - γ) when truncation
    bootstraps, much less if a time limit were treated as terminal."""

    @property
    def observation_space(self):
        return E.Box(0.0, 1.0, (2,))

    @property
    def action_space(self):
        return E.Discrete(2)

    @property
    def gamma(self):
        return 0.9

    def reset(self, *, key):
        return jnp.zeros((), jnp.int32), E.timestep(jnp.ones((2,), jnp.float32))

    def step(self, state, action, *, key):
        return state, E.timestep(jnp.ones((2,), jnp.float32), 1.0)


@pytest.mark.parametrize("memory", ["memoryless", "gru"])
def test_value_probe_bootstraps_truncation(memory):
    env = E.AutoReset(E.TimeLimit(ConstantReward(), 5))
    cfg = TrainConfig(memory=memory, hidden_size=16, num_envs=4, num_steps=32, num_minibatches=2,
                      total_steps=4 * 32 * 150, anneal_lr=False)
    hp = Hyperparams.stack([dict(cfg.grid()[0], lr=3e-3)])
    hp = jax.tree.map(lambda x: x[0], hp)
    state = init_state(cfg, env, jax.random.key(0))
    step = eqx.filter_jit(lambda s: update(cfg, env, s, hp))
    for _ in range(150):
        state, m = step(state)
    assert float(m["value_mean"]) == pytest.approx(10.0, rel=0.05)
    # 5-step episodes of reward 1: logged returns are exact
    assert float(m["return_sum"] / m["episodes"]) == pytest.approx(5.0)
    disc = sum(0.9**t for t in range(5))
    assert float(m["disc_return_sum"] / m["episodes"]) == pytest.approx(disc, rel=1e-5)


def test_rollout_unroll_changes_nothing_but_the_program():
    """`rollout_unroll` (3: not a divisor of the 64 steps) collects the same transitions as the plain loop."""
    from pobax.agent._ppo import rollout

    env = E.make("tmaze_3", action_concat=True)
    trajs = []
    for unroll in (1, 3):
        cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=4, num_minibatches=2, num_steps=64,
                          action_concat=True, rollout_unroll=unroll)
        state = init_state(cfg, env, jax.random.key(5))
        trajs.append(eqx.filter_jit(lambda s, cfg=cfg: rollout(cfg, env, s))(state))
    (s1, t1), (s3, t3) = trajs
    assert int(t1["ep_done"].sum()) > 0  # episodes ended (and reset) inside the loop
    for a, b in zip(jax.tree.leaves((t1, s1.carry, s1.obs)), jax.tree.leaves((t3, s3.carry, s3.obs))):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=1e-6)


def test_categorical_mask_and_closed_forms():
    logits = jnp.array([0.0, 1.0, 2.0])
    mask = jnp.array([True, False, True])
    d = Categorical.from_logits(logits, mask)
    p = np.exp([0.0, 2.0]) / np.exp([0.0, 2.0]).sum()
    np.testing.assert_allclose(np.exp(d.logits), [p[0], 0.0, p[1]], atol=1e-6)
    assert float(d.entropy()) == pytest.approx(-(p * np.log(p)).sum(), rel=1e-5)
    samples = jax.vmap(d.sample)(jax.random.split(jax.random.key(0), 2000))
    assert not np.any(np.asarray(samples) == 1)


def test_gaussian_log_prob_and_entropy_closed_forms():
    mean, log_std = jnp.array([0.5, -1.0]), jnp.array([0.1, -0.3])
    d = DiagGaussian(mean, log_std)
    a = jnp.array([0.2, 0.0])
    std = np.exp(np.asarray(log_std))
    ref = np.sum(-0.5 * ((np.asarray(a) - np.asarray(mean)) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi))
    assert float(d.log_prob(a)) == pytest.approx(ref, rel=1e-5)
    assert float(d.entropy()) == pytest.approx(np.sum(0.5 * np.log(2 * np.pi * np.e * std**2)), rel=1e-5)


def test_compiles_once_per_structure_and_sweeps_are_batched(tmp_path):
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 6, num_seeds=2, num_chunks=3, lr=(1e-3, 1e-4))
    before = _train.TRACE_COUNT
    r1 = train(cfg, save=False, progress=False)
    after_first = _train.TRACE_COUNT
    r2 = train(dataclasses.replace(cfg, lr=(5e-3, 5e-4), lambda0=(0.5, 0.9), seed=7), save=False, progress=False)
    assert after_first - before == 1
    # 2×2 sets instead of 1×2 changes the batch size (a new shape), but not 4 separate programs
    assert _train.TRACE_COUNT - after_first <= 1
    m = r1.metrics
    assert set(m.hp_index) == {0, 1} and set(m.seed) == {0, 1}
    assert len(m) == 2 * 2 * cfg.num_updates
    assert sorted(m.env_step.unique()) == [32 * (i + 1) for i in range(cfg.num_updates)]
    assert len(r2.metrics) == 4 * 2 * cfg.num_updates
    # different learning rates really differ
    a = m[(m.hp_index == 0) & (m.seed == 0)].pg_loss.to_numpy()
    b = m[(m.hp_index == 1) & (m.seed == 0)].pg_loss.to_numpy()
    assert not np.allclose(a, b)


def test_double_critic_logs_lambda_discrepancy():
    cfg = TrainConfig(env="tmaze_3", memory="memoryless", double_critic=True, hidden_size=8, num_envs=2,
                      num_minibatches=1, num_steps=16, total_steps=2 * 16 * 4, num_seeds=1, num_chunks=1,
                      lambda1=(0.5,), ld_weight=(0.5,))
    r = train(cfg, save=False, progress=False)
    assert "lambda_discrepancy" in r.metrics and np.isfinite(r.metrics.lambda_discrepancy).all()
    assert len(r.state.model.critics[0].out.bias) == 1 and len(r.state.model.critics) == 2


def test_lambda_discrepancy_vanishes_when_observable_and_not_under_aliasing():
    # A fully observable chain (one state, reward 1): both critics converge to 1/(1-γ), their difference to 0.
    env = E.AutoReset(E.TimeLimit(ConstantReward(), 5))
    cfg = TrainConfig(memory="memoryless", double_critic=True, hidden_size=16, num_envs=4, num_steps=32,
                      num_minibatches=2, total_steps=4 * 32 * 150, anneal_lr=False)
    hp = jax.tree.map(lambda x: x[0], Hyperparams.stack([dict(cfg.grid()[0], lr=3e-3, lambda0=0.95, lambda1=0.5)]))
    state = init_state(cfg, env, jax.random.key(0))
    step = eqx.filter_jit(lambda s: update(cfg, env, s, hp))
    for _ in range(150):
        state, m = step(state)
    # compare on the scale of the values: mean squared disagreement / mean squared value
    observable = float(m["lambda_discrepancy"]) / float(m["value_mean"]) ** 2
    # T-Maze seen by a memoryless agent: the hallway is aliased, so TD(0.5) and TD(0.95) disagree.
    r = train(TrainConfig(env="tmaze_5", memory="memoryless", double_critic=True, hidden_size=16,
                          total_steps=4 * 128 * 60, num_seeds=2, num_chunks=1, lambda0=(0.95,), lambda1=(0.5,),
                          lr=(2.5e-3,)), save=False, progress=False)
    tail = r.metrics.groupby("seed").tail(10)
    aliased = float((tail.lambda_discrepancy / tail.value_mean**2).groupby(tail.seed).mean().min())
    print(f"relative lambda discrepancy: observable {observable:.2e}, aliased {aliased:.2e}")
    assert observable < 1e-4
    assert aliased > 10 * observable


def test_episode_metrics_from_info_are_logged_per_episode(monkeypatch):
    """An environment's `episode_metrics` (info entries at episode ends) become metric columns: here the
    final reward of each T-Maze episode, whose episode mean is the mean return (only the last step pays)."""
    import equinox as eqx

    from pobax.agent import TrainConfig, train
    from pobax.env import make
    from pobax.env._base import AbstractWrapper

    def with_info(s, ts):
        return s, eqx.tree_at(lambda t: t.info, ts, {"final": jnp.stack([ts.reward, jnp.ones_like(ts.reward)])})

    class FinalReward(AbstractWrapper):
        env: object

        @property
        def episode_metrics(self):
            return {"final": ("final_reward", "always_one")}

        def reset(self, *, key):
            return with_info(*self.env.reset(key=key))

        def step(self, state, action, *, key):
            return with_info(*self.env.step(state, action, key=key))

    import pobax.agent._train as T

    cfg = TrainConfig(env="tmaze_5", memory="memoryless", hidden_size=8, num_envs=4, num_steps=32,
                      total_steps=4 * 32 * 6, num_seeds=2, num_chunks=2)
    real_make = T.make
    monkeypatch.setattr(T, "make", lambda *a, **k: FinalReward(real_make(*a, **k)))
    df = train(cfg, save=False, progress=False).metrics
    ended = df["episodes"] > 0
    assert ended.any()
    np.testing.assert_allclose(df.loc[ended, "final_reward"], df.loc[ended, "return"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(df.loc[ended, "always_one"], 1.0)
    assert df.loc[~ended, "always_one"].isna().all()


def test_chunk_compiled_from_shapes_equals_the_plain_calls():
    """`train` compiles the chunk program from abstract shapes before any state exists (on accelerators at the same
    time as the initialisation); its runs must be those of the programs compiled on concrete arguments. The chunk
    donates the state it is given."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 4, num_seeds=2, num_chunks=2)
    _train.clear_compiled()
    r = train(cfg, save=False, progress=False)
    _train.clear_compiled()
    env = E.make(cfg.env, cfg.observability)
    scfg, hp = _train.structural(cfg), _train.run_hyperparams(cfg)
    state = _train._init(cfg, env, _train.run_layout(cfg)[1])
    chunk_len = _train.chunk_length(cfg)
    for start in range(0, cfg.num_updates, chunk_len):
        given = jax.tree.leaves(state)
        state, _ = _train._chunk(scfg, env, state, hp, start, chunk_len)
        # the chunk donates the state it was given: its buffers now hold the new state, not two copies
        assert all(x.is_deleted() for x in given)
        assert not any(x.is_deleted() for x in jax.tree.leaves(state))
    for a, b in zip(jax.tree.leaves(eqx.filter(r.state.model, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(state.model, eqx.is_array))):
        np.testing.assert_array_equal(a, b)


def test_one_run_without_the_vmap_trains_the_same_run(monkeypatch):
    """`SINGLE_RUN_UNBATCHED`: one run's programs traced without the `vmap` over runs compute the same initial state
    and updates (to float rounding: XLA fuses them a little differently) as under the `vmap`."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 3, num_seeds=1, num_chunks=1)
    runs = []
    for unbatched in (True, False):
        monkeypatch.setattr(_train, "SINGLE_RUN_UNBATCHED", unbatched)
        _train.clear_compiled()
        runs.append(train(cfg, save=False, progress=False))
    _train.clear_compiled()
    a, b = (jax.tree.leaves(eqx.filter(r.state.model, eqx.is_array)) for r in runs)
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert x.shape == y.shape and x.shape[0] == 1  # the run axis is put back
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(runs[0].metrics["v_loss"], runs[1].metrics["v_loss"], rtol=1e-4)
    start = jax.tree.leaves(eqx.filter(_train._init(cfg, E.make(cfg.env), np.zeros(1, np.int32)).model, eqx.is_array))
    assert any(np.abs(np.asarray(x) - np.asarray(s0)).max() > 1e-4 for x, s0 in zip(a, start))  # the updates moved it


@pytest.mark.parametrize("seed", [0, 2**31 + 5, 2**32 + 7])
def test_initialisation_keys_are_those_of_the_base_seed(seed):
    """The initialisation program derives the runs' keys from the seed itself: they must be the host's
    `jax.random.split(jax.random.key(seed), num_seeds)[run_seed]`, large seeds included."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 2, num_seeds=3, seed=seed)
    env = E.make(cfg.env, cfg.observability)
    run_seed = np.array([2, 0, 1, 2])
    states = _train._init(cfg, env, run_seed)
    keys = jax.random.split(jax.random.key(seed), cfg.num_seeds)[run_seed]
    expected = jax.vmap(lambda k: init_state(_train.structural(cfg), env, k))(keys)
    np.testing.assert_array_equal(jax.random.key_data(states.key), jax.random.key_data(expected.key))
    for a, b in zip(jax.tree.leaves(eqx.filter(states.model, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(expected.model, eqx.is_array))):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


def test_gpu_compiler_options_only_on_nvidia_and_yield_to_xla_flags(monkeypatch):
    """The programs get `GPU_COMPILER_OPTIONS` on an NVIDIA GPU only, and an option the user set in $XLA_FLAGS is
    theirs."""
    assert _train.compiler_options() == {} or _train._on_nvidia_gpu()
    monkeypatch.setattr(_train, "_on_nvidia_gpu", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level=2")
    assert _train.compiler_options() == _train.GPU_COMPILER_OPTIONS != {}
    assert _train.compiler_options({"xla_gpu_enable_triton_gemm": False}) == {
        **_train.GPU_COMPILER_OPTIONS, "xla_gpu_enable_triton_gemm": False}
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level=2 --xla_gpu_experimental_autotune_backends=TRITON")
    assert "xla_gpu_experimental_autotune_backends" not in _train.compiler_options()


def test_products_are_classified_in_nested_jaxprs():
    """`_products` sees the matrix products inside a loop and a branch: "tf32" (the TF32 algorithm), "default"
    (DEFAULT precision given explicitly), "unplaced" (another precision or none, or a convolution)."""
    def f(x, precision, conv=False):
        def body(c, _):
            def product(c):
                if conv:
                    return jax.lax.conv(c[None, None], c[None, None], (1, 1), "SAME")[0, 0]
                return jnp.matmul(c, c, precision=precision)
            return jax.lax.cond(c[0, 0] > 0, product, lambda c: c + 1.0, c), None
        return jax.lax.scan(body, jnp.matmul(x, x, precision=jax.lax.Precision.DEFAULT), None, length=2)[0]

    x = jnp.ones((3, 3))
    assert _train._products(jax.make_jaxpr(lambda x: f(x, None))(x)) == {"default", "unplaced"}
    assert _train._products(jax.make_jaxpr(lambda x: f(x, jax.lax.Precision.DEFAULT))(x)) == {"default"}
    tf32 = jax.lax.DotAlgorithmPreset.TF32_TF32_F32
    assert _train._products(jax.make_jaxpr(lambda x: f(x, tf32))(x)) == {"default", "tf32"}
    assert "unplaced" in _train._products(jax.make_jaxpr(lambda x: f(x, jax.lax.Precision.DEFAULT, conv=True))(x))
    assert _train._products(jax.make_jaxpr(lambda x: f(x, jax.lax.Precision.HIGHEST))(x)) == {"default", "unplaced"}


def test_split_gemms_keeps_the_function_and_places_every_product():
    """Within `split_gemms`: a product over a sequence is the same function (values and gradients) behind
    optimization barriers, forward and backward; a product inside a loop carries the TF32 algorithm (XLA's GEMM
    fusion gives it to Triton); outside, products are plain."""
    import pobax.memory._layers as L  # noqa: PLC0415

    x, w = jax.random.normal(jax.random.key(0), (5, 3)), jax.random.normal(jax.random.key(1), (4, 3))

    def loss(x, w):
        return jnp.sum(jnp.tanh(L.matmul_t(x, w)) ** 2)

    plain = jax.value_and_grad(loss, argnums=(0, 1))(x, w)
    with L.split_gemms():
        split = jax.value_and_grad(loss, argnums=(0, 1))(x, w)
        jaxpr = str(jax.make_jaxpr(jax.grad(loss, argnums=(0, 1)))(x, w))
        loop = str(jax.make_jaxpr(L.loop_matmul)(w, x[0]))
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(split)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    assert jaxpr.count("optimization_barrier") == 4  # inputs and output forward, their cotangents backward
    assert jaxpr.count("dot_general") == 3 and "precision=None" not in jaxpr
    assert "TF32_TF32_F32" in loop
    assert "optimization_barrier" not in str(jax.make_jaxpr(jax.grad(loss))(x, w))


def _chunk_options(cfg: TrainConfig) -> dict:
    """The options the chunk program of `cfg` gets (traced as `train` does; not lowered: this CPU cannot lower the
    TF32 algorithm that `split_gemms` gives the loops' products)."""
    env = E.make(cfg.env, cfg.observability, action_concat=cfg.action_concat)
    key, low = _train._INIT.lower(*_train._init_args(cfg, env, _train.run_layout(cfg)[1]))
    state = _train._INIT.out_shapes(key, low)
    args = (_train.structural(cfg), env, state, _train.run_hyperparams(cfg), jax.ShapeDtypeStruct((), jnp.int32),
            _train.chunk_length(cfg))
    static, dynamic = _train._partition(args)
    _train.clear_compiled()  # JAX keeps traces: the module-level switches below are read when tracing
    with _train._CHUNK._lowering(args):
        jaxpr = _train._CHUNK._jit(args).trace(static, *dynamic).jaxpr
    return _train._CHUNK._options(args, jaxpr)


def test_gemms_are_split_only_for_wide_networks_whose_products_are_all_placed(monkeypatch):
    """The GPU rule `CUBLAS_MIN_HIDDEN`: a wide network's one-run chunk program gets `SPLIT_OPTIONS` on a TF32 GPU, with
    `DETERMINISTIC_OPTIONS` where no loop has a product (the rollout's layers multiply-sums, the recurrence too),
    and XLA's defaults where there are several runs, the network is narrow, the program has products the network did not place
    (attention), the rule is off, $XLA_FLAGS chooses the GEMM backend, or the machine is not such a GPU."""
    import pobax.memory._gru as gru_mod  # noqa: PLC0415
    import pobax.memory._layers as layers_mod  # noqa: PLC0415

    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=256, num_envs=2, num_minibatches=2, num_steps=8,
                      total_steps=2 * 8 * 2, num_seeds=1, num_chunks=1)
    split, det = _train.SPLIT_OPTIONS, {**_train.SPLIT_OPTIONS, **_train.DETERMINISTIC_OPTIONS}
    monkeypatch.setattr(layers_mod, "REDUCE_MAX_WORK", 2**22)  # the rollout's layers as on a GPU
    monkeypatch.setattr(gru_mod, "RECURRENT_IMPL", "reduce")
    assert _chunk_options(cfg) == (det if _train._tf32_gpu() else {})  # this machine's own answer
    monkeypatch.setattr(_train, "_tf32_gpu", lambda: True)
    assert _chunk_options(cfg) == det
    assert _chunk_options(dataclasses.replace(cfg, memory="memoryless")) == det
    assert _chunk_options(dataclasses.replace(cfg, num_seeds=2)) == {}  # batched runs: XLA's defaults
    monkeypatch.setattr(gru_mod, "RECURRENT_IMPL", "dot")  # the recurrence a product in the loops: Triton's
    assert _chunk_options(cfg) == split
    monkeypatch.setattr(gru_mod, "RECURRENT_IMPL", "reduce")
    assert _chunk_options(dataclasses.replace(cfg, hidden_size=128)) == {}
    trxl = dataclasses.replace(cfg, memory="trxl", num_heads=2, num_layers=1, embed_size=16)
    assert _chunk_options(trxl) == {}  # attention's products
    monkeypatch.setattr(_train, "CUBLAS_MIN_HIDDEN", None)
    assert _chunk_options(cfg) == {}
    monkeypatch.setattr(_train, "CUBLAS_MIN_HIDDEN", 256)
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_triton_gemm_any=true")  # the user's choice turns the rule off
    assert _chunk_options(cfg) == {}


def test_one_narrow_run_gets_one_triton_tiling(monkeypatch, tmp_path):
    """The GPU rule `TILING_MAX_HIDDEN`: one run of a narrow network whose products are all the network's gets
    `GEMM_TILING` (a file XLA reads, named by its content) on a TF32 GPU; several runs, a wider network, attention's
    products, the rule off, or the option in $XLA_FLAGS leave XLA's autotuning."""
    import pobax.memory._gru as gru_mod  # noqa: PLC0415
    import pobax.memory._layers as layers_mod  # noqa: PLC0415

    monkeypatch.setenv("POBAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(layers_mod, "REDUCE_MAX_WORK", 2**22)  # the rollout's layers as on a GPU
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=32, num_envs=2, num_minibatches=2, num_steps=8,
                      total_steps=2 * 8 * 2, num_seeds=1, num_chunks=1)
    assert _chunk_options(cfg) == {} or _train._tf32_gpu()  # this machine's own answer
    monkeypatch.setattr(_train, "_tf32_gpu", lambda: True)
    for impl in ("dot", "reduce"):  # the recurrence a product in the loop or a multiply-sum
        monkeypatch.setattr(gru_mod, "RECURRENT_IMPL", impl)
        options = _chunk_options(cfg)
        assert list(options) == [_train.TILING_OPTION]
        path = Path(options[_train.TILING_OPTION])
        assert path.parent == tmp_path and path.read_text() == _train.GEMM_TILING
    assert _chunk_options(dataclasses.replace(cfg, memory="memoryless")) == options
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    monkeypatch.setenv("POBAX_CACHE_DIR", str(blocked / "cache"))  # an unwritable cache: the temporary directory
    assert Path(_train._tiling_file()).read_text() == _train.GEMM_TILING
    assert Path(_train._tiling_file()).parent == Path(tempfile.gettempdir())
    monkeypatch.setenv("POBAX_CACHE_DIR", str(tmp_path))
    assert _chunk_options(dataclasses.replace(cfg, num_seeds=2)) == {}  # batched runs: XLA's autotuning
    assert _chunk_options(dataclasses.replace(cfg, hidden_size=128)) == {}
    trxl = dataclasses.replace(cfg, memory="trxl", num_heads=2, num_layers=1, embed_size=16)
    assert _chunk_options(trxl) == {}  # attention's products
    monkeypatch.setattr(_train, "TILING_MAX_HIDDEN", None)
    assert _chunk_options(cfg) == {}
    monkeypatch.setenv("XLA_FLAGS", f"--{_train.TILING_OPTION}=/elsewhere.textproto")  # the user's file wins
    assert _train.TILING_OPTION not in _train.compiler_options(options)


def test_a_tiling_xla_cannot_compile_gives_way_to_its_autotuning(monkeypatch):
    """Where XLA fails to compile a program with `GEMM_TILING`, it is compiled without it, with a warning, keeping its
    other options."""
    class Lowered:
        def compile(self, compiler_options=None):
            if _train.TILING_OPTION in (compiler_options or {}):
                raise jax.errors.JaxRuntimeError("INTERNAL: Could not parse override file")
            return compiler_options

    monkeypatch.setattr(_train, "_on_nvidia_gpu", lambda: False)
    with pytest.warns(UserWarning, match=_train.TILING_OPTION):
        assert _train._compile(Lowered(), {_train.TILING_OPTION: "/x", "xla_gpu_autotune_level": 4}) == {
            "xla_gpu_autotune_level": 4}


def test_deterministic_ops_that_xla_cannot_compile_are_dropped_with_a_warning(monkeypatch):
    """Where XLA cannot compile a program with `DETERMINISTIC_OPTIONS` (a Triton GEMM left in it), the program is
    compiled without them, with a warning, keeping its other options; other errors are raised."""
    class Lowered:
        def compile(self, compiler_options=None):
            if "xla_gpu_deterministic_ops" in (compiler_options or {}):
                raise jax.errors.JaxRuntimeError("INTERNAL: No supported config found for HLO: gemm_fusion")
            return compiler_options

    monkeypatch.setattr(_train, "_on_nvidia_gpu", lambda: False)
    with pytest.warns(UserWarning, match="xla_gpu_deterministic_ops"):
        assert _train._compile(Lowered(), {**_train.SPLIT_OPTIONS, **_train.DETERMINISTIC_OPTIONS}) == _train.SPLIT_OPTIONS

    class Broken:
        def compile(self, compiler_options=None):
            raise jax.errors.JaxRuntimeError("INTERNAL: something else")

    with pytest.raises(jax.errors.JaxRuntimeError, match="something else"):
        _train._compile(Broken(), dict(_train.SPLIT_OPTIONS))


def test_an_option_this_xla_does_not_know_is_dropped_with_a_warning(monkeypatch):
    """A compile option that another XLA version does not have must not stop training: the program is compiled
    without it, once warned, and the run is the one compiled without options."""
    cfg = TrainConfig(env="tmaze_3", memory="memoryless", hidden_size=8, num_envs=2, num_minibatches=2,
                      num_steps=16, total_steps=2 * 16 * 2, num_seeds=1, num_chunks=1)
    _train.clear_compiled()
    plain = train(cfg, save=False, progress=False)
    _train.clear_compiled()
    monkeypatch.setattr(_train, "_on_nvidia_gpu", lambda: True)
    monkeypatch.setattr(_train, "GPU_COMPILER_OPTIONS", {"xla_gpu_no_such_option_anywhere": "1"})
    monkeypatch.setattr(_train, "_UNKNOWN_OPTIONS", set())
    with pytest.warns(UserWarning, match="xla_gpu_no_such_option_anywhere"):
        r = train(cfg, save=False, progress=False)
    assert _train.compiler_options() == {}  # not tried again in this process
    _train.clear_compiled()
    for a, b in zip(jax.tree.leaves(eqx.filter(r.state.model, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(plain.state.model, eqx.is_array))):
        np.testing.assert_array_equal(a, b)
