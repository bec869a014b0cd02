"""Observation normalisation: running moments, per-run state, what the agent and the replay see."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pobax.env as E
from pobax.agent import TrainConfig, init_state, rollout
from pobax.eval import train
from pobax.agent._ppo import ObsNorm


def test_running_moments_match_numpy():
    rng = np.random.default_rng(0)
    data = rng.normal(3.0, 2.0, (40, 8, 5)).astype(np.float32) * np.arange(1, 6, dtype=np.float32)
    norm = ObsNorm.init((5,))
    for batch in data:
        norm = norm.update(jnp.asarray(batch))
    flat = data.reshape(-1, 5)
    np.testing.assert_allclose(norm.mean, flat.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(norm.var, flat.var(0), rtol=1e-3)
    z = np.asarray(norm(jnp.asarray(flat)))
    np.testing.assert_allclose(z.mean(0), 0.0, atol=1e-3)
    np.testing.assert_allclose(z.std(0), 1.0, atol=1e-3)
    # an action mask travels unchanged; the observation proper is normalised
    d = norm({"obs": jnp.asarray(flat[:3]), "action_mask": jnp.ones((3, 2), bool)})
    assert d["action_mask"].dtype == jnp.bool_
    np.testing.assert_allclose(d["obs"], z[:3], atol=1e-6)


def test_rollout_stores_normalised_observations():
    env = E.make("tmaze_5")
    cfg = TrainConfig(env="tmaze_5", memory="memoryless", normalize_obs=True, hidden_size=8, num_envs=4,
                      num_steps=16, num_minibatches=2, total_steps=4 * 16 * 2)
    state = init_state(cfg, env, jax.random.key(0))
    assert state.obs_norm is not None
    norm = state.obs_norm.update(E.observation_array(state.obs))
    new_state, traj = eqx.filter_jit(lambda s: rollout(cfg, env, s))(state)
    # the first stored observation is the initial one, normalised by the statistics after seeing it
    np.testing.assert_allclose(traj["obs"][0], norm(state.obs), atol=1e-6)
    assert float(new_state.obs_norm.count) == pytest.approx(16 * 4, abs=1e-3)
    assert np.all(np.abs(np.asarray(traj["obs"])) <= 10.0)


@pytest.mark.slow
def test_statistics_are_per_run_and_off_by_default():
    cfg = TrainConfig(env="tmaze_5", memory="memoryless", normalize_obs=True, hidden_size=8, num_envs=4,
                      num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3, num_seeds=2, num_chunks=1)
    r = train(cfg, save=False, progress=False)
    counts = np.asarray(r.state.obs_norm.count)
    assert counts.shape == (2,)  # one set of statistics per run (vmapped)
    np.testing.assert_allclose(counts, 3 * 16 * 4, atol=1e-2)
    assert not np.allclose(r.state.obs_norm.mean[0], r.state.obs_norm.mean[1])  # seeds see different episodes
    assert np.isfinite(r.metrics["pg_loss"]).all()
    plain = init_state(TrainConfig(env="tmaze_5", num_envs=4), E.make("tmaze_5"), jax.random.key(0))
    assert plain.obs_norm is None


def test_reward_scaling_follows_discounted_return_std():
    from pobax.agent._ppo import RewardNorm

    rng = np.random.default_rng(1)
    rewards = rng.normal(5.0, 3.0, (60, 4)).astype(np.float32)
    dones = rng.random((60, 4)) < 0.1
    rn = RewardNorm.init(4)
    ret, rets = np.zeros(4), []
    for r, d in zip(rewards, dones):
        rn, out = rn(jnp.asarray(r), jnp.asarray(d), 0.9)
        ret = ret * 0.9 + r
        rets.append(ret.copy())
        expected_var = np.concatenate(rets).var()
        np.testing.assert_allclose(out, r / np.sqrt(expected_var + 1e-8), rtol=2e-3)
        ret = np.where(d, 0.0, ret)
        np.testing.assert_allclose(rn.ret, ret, rtol=1e-5)


def test_normalising_image_observations_is_refused_not_ignored(tmp_path):
    """Images are scaled by their encoder; `--normalize-obs` on one is refused (exit 2) before a run directory is
    written, where it used to be silently ignored."""
    import cli

    from pobax.agent import ConfigError, Runs

    pytest.importorskip("navix")
    maze = "Navix-DMLab-Maze-01-v0"  # the full view is a map (21, 41, 6)
    with pytest.raises(ConfigError, match="applies to vector observations; .* full observation is an image"):
        Runs(TrainConfig(env=maze, observability="full", memory="memoryless", normalize_obs=True, num_envs=4))
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--env", maze, "--observability", "full", "--memory", "memoryless", "--normalize-obs",
                  "--num-envs", "4", "--total-steps", "512", "--out", str(out)])
    assert e.value.code == 2 and not out.exists()
