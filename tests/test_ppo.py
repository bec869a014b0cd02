import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pobax.env as E
from pobax.agent import Categorical, DiagGaussian, Hyperparams, Runs, TrainConfig, init_state, update
from pobax.agent import _train
from pobax.eval import train

from _envs import ConstantReward
from _traces import count_traces


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_compiles_once_per_structure_and_sweeps_are_batched(tmp_path):
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 6, num_seeds=2, num_chunks=3, lr=(1e-3, 1e-4))
    with count_traces("_chunk_runs") as first:
        r1 = train(cfg, save=False, progress=False)
    with count_traces("_chunk_runs") as second:
        r2 = train(dataclasses.replace(cfg, lr=(5e-3, 5e-4), lambda0=(0.5, 0.9), seed=7), save=False, progress=False)
    assert first[0] == 1
    # 2×2 sets instead of 1×2 changes the batch size (a new shape), but not 4 separate programs
    assert second[0] <= 1
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_episode_metrics_from_info_are_logged_per_episode():
    """An environment's `episode_metrics` (info entries at episode ends) become metric columns: here the
    final reward of each T-Maze episode, whose episode mean is the mean return (only the last step pays)."""
    import equinox as eqx

    from pobax.agent import TrainConfig

    from pobax.eval import train
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

    cfg = TrainConfig(env="tmaze_5", memory="memoryless", hidden_size=8, num_envs=4, num_steps=32,
                      total_steps=4 * 32 * 6, num_seeds=2, num_chunks=2)
    result = train(cfg, save=False, progress=False, env=FinalReward(make("tmaze_5", "partial")))
    df = result.metrics
    ended = df["episodes"] > 0
    assert ended.any()
    np.testing.assert_allclose(df.loc[ended, "final_reward"], df.loc[ended, "return"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(df.loc[ended, "always_one"], 1.0)
    assert df.loc[~ended, "always_one"].isna().all()
    # The summary carries their final values per seed, as it does the returns'.
    final = result.summary["sets"][0]["episode_metrics"]
    assert set(final) == {"final_reward", "always_one"}
    np.testing.assert_allclose(final["final_reward"]["per_seed"], result.summary["sets"][0]["return"]["per_seed"],
                               rtol=1e-5)
    assert final["always_one"]["mean"] == pytest.approx(1.0)


@pytest.mark.slow
def test_chunks_donate_the_state_they_are_given():
    """Each chunk writes the new training state into the buffers of the one it was given (one copy on the device, not
    two); a run trained chunk by chunk equals `train`'s."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 4, num_seeds=2, num_chunks=2)
    r = train(cfg, save=False, progress=False)
    runs = Runs(cfg)
    state = runs.init()
    for chunk in runs.chunks(state):
        assert all(x.is_deleted() for x in jax.tree.leaves(state))
        state = chunk.state
        assert not any(x.is_deleted() for x in jax.tree.leaves(state))
    for a, b in zip(jax.tree.leaves(eqx.filter(r.state.model, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(state.model, eqx.is_array))):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_one_run_without_the_vmap_trains_the_same_run():
    """One run's programs are traced without the `vmap` over runs: the same initial state and updates (to float
    rounding: XLA fuses them a little differently) as the same run under the `vmap` beside another."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 3, num_seeds=1, num_chunks=1, lr=2.5e-3)
    one = train(cfg, save=False, progress=False)
    two = train(dataclasses.replace(cfg, lr=(2.5e-3, 1e-3)), save=False, progress=False)  # set 0 beside another
    a = jax.tree.leaves(eqx.filter(one.state.model, eqx.is_array))
    b = jax.tree.leaves(eqx.filter(two.state.model, eqx.is_array))
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert x.shape[0] == 1 and y.shape[0] == 2  # the run axis is put back
        np.testing.assert_allclose(x[0], y[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(one.metrics["v_loss"], two.metrics[two.metrics.hp_index == 0]["v_loss"], rtol=1e-4)
    start = jax.tree.leaves(eqx.filter(Runs(cfg).init().model, eqx.is_array))
    assert any(np.abs(np.asarray(x) - np.asarray(s0)).max() > 1e-4 for x, s0 in zip(a, start))  # the updates moved it


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2**31 + 5, 2**32 - 1])  # 2**32 and above are refused (test_hostile)
def test_initialisation_keys_are_those_of_the_base_seed(seed):
    """Each run starts from its seed's key of the base seed, the host's
    `jax.random.split(jax.random.key(seed), num_seeds)[seed_index]`, the largest seed included, whatever set it is
    in."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 2, num_seeds=3, seed=seed, lr=(1e-3, 2e-3))
    runs = Runs(cfg, devices=jax.devices()[:1])
    states = runs.init()
    seed_index = np.array([0, 1, 2, 0, 1, 2])  # two sets × three seeds, each set's seeds next to each other
    keys = jax.random.split(jax.random.key(seed), cfg.num_seeds)[seed_index]
    expected = jax.vmap(lambda k: init_state(_train.structural(cfg), runs.env, k, runs.backend))(keys)
    np.testing.assert_array_equal(jax.random.key_data(states.key), jax.random.key_data(expected.key))
    for a, b in zip(jax.tree.leaves(eqx.filter(states.model, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(expected.model, eqx.is_array))):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


@pytest.mark.slow
def test_a_rerun_of_as_many_runs_as_a_sweep_reuses_its_programs():
    """The programs depend on the number of runs, not on their sets and seeds: 2 sets × 2 seeds, then 1 set × 4
    seeds at another base seed (a protocol's smoke sweep and its rerun) trace each program once."""
    base = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                       total_steps=2 * 16 * 2, num_chunks=1)
    sweep = dataclasses.replace(base, lr=(1e-3, 2e-3), num_seeds=2, seed=3)
    rerun = dataclasses.replace(base, lr=2e-3, num_seeds=4, seed=1003)
    jax.clear_caches()
    with count_traces("_init_runs") as init, count_traces("_chunk_runs") as chunk:
        results = [train(cfg, save=False, progress=False) for cfg in (sweep, rerun)]
    assert (init[0], chunk[0]) == (1, 1)
    # the rerun really trained its own runs: other keys, so other returns
    assert not np.allclose(results[0].metrics.pg_loss, results[1].metrics.pg_loss)


def test_backend_options():
    """XLA options come from the configuration alone: `fast_compile` turns LLVM's optimisations off on any backend;
    `deterministic` asks a GPU for deterministic ops and no autotuning (a CPU is deterministic already)."""
    from pobax._backend import compiler_options

    assert compiler_options() == {}
    assert compiler_options(fast_compile=True)["xla_backend_optimization_level"] == 0
    assert compiler_options(deterministic=True) == ({} if jax.default_backend() != "gpu" else
                                                    {"xla_gpu_deterministic_ops": True, "xla_gpu_autotune_level": 0})


@pytest.mark.slow
def test_fast_compile_trains_the_same_run():
    """`fast_compile` changes how XLA compiles the programs, not what they compute (to float rounding)."""
    cfg = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                      total_steps=2 * 16 * 3, num_seeds=2, num_chunks=1)
    a, b = (train(dataclasses.replace(cfg, fast_compile=f), save=False, progress=False) for f in (False, True))
    np.testing.assert_allclose(a.metrics["v_loss"], b.metrics["v_loss"], rtol=1e-4)
    np.testing.assert_allclose(a.metrics["return"], b.metrics["return"], rtol=1e-5)


class Counter(ConstantReward):
    """The observation counts the steps of the episode (`(steps / 10, 1)`); reward 0; never terminates."""

    def reset(self, *, key):
        return jnp.zeros((), jnp.int32), E.timestep(jnp.array([0.0, 1.0]))

    def step(self, state, action, *, key):
        state = state + 1
        return state, E.timestep(jnp.stack([state / 10.0, 1.0]), 0.0)


@pytest.mark.parametrize("memory", ["memoryless", "gru"])
def test_rollout_values_and_bootstraps_are_the_networks(memory):
    """Replaying the rollout's observations one step at a time from its initial carry gives the values it recorded,
    and `next_values[t]` is the network's value of the observation that followed step t in its episode, from the
    carry after step t without a reset: the next observation, or at a time limit the final one (5 steps counted),
    never the reset observation that replaced it."""
    from pobax.agent._ppo import rollout

    env = E.AutoReset(E.TimeLimit(Counter(), 5))
    cfg = TrainConfig(memory=memory, hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16)
    state = init_state(cfg, env, jax.random.key(3))
    new_state, traj = eqx.filter_jit(lambda s: rollout(cfg, env, s))(state)
    assert bool(traj["truncated"].any()) and not bool(traj["terminated"].any())
    model = state.model
    call = eqx.filter_jit(lambda c, o, s: model(c, o[None], s[None]))
    for e in range(cfg.num_envs):
        carry = jax.tree.map(lambda a: a[e], state.carry)
        for t in range(cfg.num_steps):
            carry, _, values = call(carry, traj["obs"][t, e], traj["starts"][t, e])
            np.testing.assert_allclose(values[0], traj["values"][t, e], rtol=1e-5, atol=1e-6)
            if traj["truncated"][t, e]:
                following = jnp.array([0.5, 1.0])
                assert not np.allclose(following, traj["obs"][t + 1, e] if t + 1 < cfg.num_steps else
                                       new_state.obs[e])
            else:
                following = traj["obs"][t + 1, e] if t + 1 < cfg.num_steps else new_state.obs[e]
            _, _, bootstrap = call(carry, following, jnp.asarray(False))
            np.testing.assert_allclose(bootstrap[0], traj["next_values"][t, e], rtol=1e-5, atol=1e-6)


def test_normalize_advantages_off_keeps_the_advantages_scale():
    """The policy-gradient term scales with the advantages when they are not standardised, and is unchanged by
    their scale when they are."""
    from pobax.agent._ppo import make_model, ppo_loss

    env = ConstantReward()
    cfg = TrainConfig(memory="memoryless", hidden_size=8)
    model = make_model(cfg, env, jax.random.key(0))
    hp = jax.tree.map(lambda x: x[0], Hyperparams.stack([dict(cfg.grid()[0], lr=1e-3)]))
    T, B = 6, 2
    obs = jnp.ones((T, B, 2))
    starts = jnp.zeros((T, B), bool).at[0].set(True)
    _, dist, values = jax.vmap(model, in_axes=(0, 1, 1), out_axes=(0, 1, 1))(
        jax.tree.map(lambda c: jnp.broadcast_to(c, (B, *c.shape)), model.init_carry()), obs, starts)
    action = jnp.tile(jnp.array([0, 1]), (T, 1))
    adv = jax.random.normal(jax.random.key(1), (T, B)) + 0.5
    mb = dict(carry=jax.tree.map(lambda c: jnp.broadcast_to(c, (B, *c.shape)), model.init_carry()), obs=obs,
              starts=starts, action=action, values=values, targets=values,
              logp=dist.log_prob(action) - 0.1 * jax.random.normal(jax.random.key(2), (T, B)))

    def pg(scale, normalize):
        _, stats = ppo_loss(model, dict(mb, advantages=scale * adv), hp, False, normalize_advantages=normalize)
        return float(stats["pg_loss"])

    assert pg(1.0, True) == pytest.approx(pg(10.0, True), rel=1e-4)
    assert pg(10.0, False) == pytest.approx(10.0 * pg(1.0, False), rel=1e-4)
    assert abs(pg(1.0, False) - pg(1.0, True)) > 1e-3
    assert TrainConfig().normalize_advantages  # the default keeps the usual PPO


@pytest.mark.slow
def test_reward_scale_scales_what_is_learnt_from_not_what_is_logged():
    """`reward_scale` multiplies the rollout's rewards (and so the value targets) but not the logged returns."""
    from pobax.agent import ConfigError, validate
    from pobax.agent._ppo import init_state, rollout

    env = ConstantReward()
    out = {}
    for scale in (1.0, 3.0):
        cfg = TrainConfig(memory="memoryless", hidden_size=8, num_envs=2, num_steps=5, reward_scale=scale)
        state = init_state(cfg, env, jax.random.key(0))
        _, traj = rollout(cfg, env, state)
        out[scale] = traj
    np.testing.assert_allclose(out[3.0]["reward"], 3.0 * np.asarray(out[1.0]["reward"]))
    np.testing.assert_allclose(out[3.0]["ep_return"], out[1.0]["ep_return"])
    assert float(out[1.0]["reward"].sum()) > 0
    with pytest.raises(ConfigError, match="--reward-scale must be > 0"):
        validate(TrainConfig(reward_scale=0.0))
