import pytest
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import pobax.env as E

KEY = jax.random.key(0)


class Counter(E.AbstractEnvironment):
    """Observation = number of steps taken; terminates when the action is 1."""

    @property
    def observation_space(self):
        return E.Box(0.0, 1e9, (1,))

    @property
    def action_space(self):
        return E.Discrete(2)

    @property
    def gamma(self):
        return 0.9

    def reset(self, *, key):
        return jnp.zeros((), jnp.int32), E.timestep(jnp.zeros((1,), jnp.float32))

    def step(self, state, action, *, key):
        t = state + 1
        return t, E.timestep(t[None].astype(jnp.float32), 1.0, terminated=action == 1)


def test_auto_reset_keeps_final_obs_and_starts_next_episode():
    env = E.AutoReset(E.TimeLimit(Counter(), 3))
    s, ts = env.reset(key=KEY)
    obs, final, term, trunc = [], [], [], []
    for a in [0, 0, 0, 0, 1, 0]:
        s, ts = env.step(s, jnp.int32(a), key=KEY)
        obs.append(float(ts.obs[0]))
        final.append(float(ts.final_obs[0]))
        term.append(bool(ts.terminated))
        trunc.append(bool(ts.truncated))
    # Truncated after 3 steps (final obs 3, next obs 0); then a termination on the 2nd step of episode 2.
    assert obs == [1, 2, 0, 1, 0, 1]
    assert final == [1, 2, 3, 1, 2, 1]
    assert trunc == [False, False, True, False, False, False]
    assert term == [False, False, False, False, True, False]


def test_time_limit_does_not_truncate_a_terminal_step():
    env = E.TimeLimit(Counter(), 2)
    s, _ = env.reset(key=KEY)
    s, _ = env.step(s, jnp.int32(0), key=KEY)
    s, ts = env.step(s, jnp.int32(1), key=KEY)
    assert bool(ts.terminated) and not bool(ts.truncated)


def test_action_concat_one_hot_after_observation():
    env = E.make("tmaze_3", "full", action_concat=True)
    assert env.observation_space.shape == (8,)
    s, ts = env.reset(key=KEY)
    np.testing.assert_array_equal(ts.obs[4:], 0.0)
    s, ts = env.step(s, jnp.int32(2), key=KEY)
    np.testing.assert_array_equal(ts.obs[4:], [0, 0, 1, 0])
    np.testing.assert_array_equal(ts.final_obs, ts.obs)
    # the observability variant is still there: full shows a cue bit in the corridor position too
    assert float(ts.obs[:2].sum()) == 1.0


def test_action_concat_images_become_channels():
    class Img(Counter):
        @property
        def observation_space(self):
            return E.Box(0.0, 1.0, (2, 3, 2))

        def reset(self, *, key):
            return jnp.zeros((), jnp.int32), E.timestep(jnp.ones((2, 3, 2)))

        def step(self, state, action, *, key):
            return state + 1, E.timestep(jnp.ones((2, 3, 2)), 0.0)

    env = E.ActionConcat(Img())
    assert env.observation_space.shape == (2, 3, 4)
    s, ts = env.reset(key=KEY)
    s, ts = env.step(s, jnp.int32(1), key=KEY)
    assert ts.obs.shape == (2, 3, 4)
    np.testing.assert_array_equal(ts.obs[..., 2], 0.0)
    np.testing.assert_array_equal(ts.obs[..., 3], 1.0)


def test_timestep_done():
    ts = E.timestep(jnp.zeros(1), 0.0, terminated=False, truncated=True)
    assert bool(ts.done)
    assert eqx.tree_equal(ts, ts)


class UInt8Image(E.AbstractEnvironment):
    """A 4×4×3 uint8 image (all 255 at reset, random after) with the given action space."""

    actions: E.Discrete | E.Box = eqx.field(static=True)

    @property
    def observation_space(self):
        return E.Box(0.0, 255.0, (4, 4, 3), jnp.uint8)

    @property
    def action_space(self):
        return self.actions

    @property
    def gamma(self):
        return 0.99

    def reset(self, *, key):
        return jnp.zeros(()), E.timestep(jnp.full((4, 4, 3), 255, jnp.uint8))

    def step(self, state, action, *, key):
        return state, E.timestep(jax.random.randint(key, (4, 4, 3), 0, 256).astype(jnp.uint8))


def test_action_concat_keeps_continuous_actions_on_uint8_images():
    """A continuous action on a uint8 image: the image is scaled to float32 in [0, 1] first, so actions in
    [-1, 1] survive."""
    base = UInt8Image(E.Box(-1.0, 1.0, (2,)))
    env = E.ActionConcat(base)
    _, ts = env.step(jnp.zeros(()), jnp.array([-0.5, 0.75]), key=KEY)
    _, raw = base.step(jnp.zeros(()), jnp.array([-0.5, 0.75]), key=KEY)
    assert ts.obs.dtype == jnp.float32 and ts.obs.shape == env.observation_space.shape == (4, 4, 5)
    np.testing.assert_allclose(ts.obs[..., :3], raw.obs / 255.0, atol=1e-6)
    np.testing.assert_allclose(ts.obs[0, 0, 3:], [-0.5, 0.75])
    assert env.observation_space.low == -1.0 and env.observation_space.high == 1.0


def test_action_concat_keeps_uint8_images_with_discrete_actions_and_encodes_the_same():
    """A one-hot action on a uint8 image stays uint8 (0/255 planes): after the encoders' scaling it equals
    the float path (image / 255 with 0/1 planes), at a quarter of the memory."""
    from pobax.agent import make_encoder

    base = UInt8Image(E.Discrete(5))
    env = E.ActionConcat(base)
    _, ts = env.step(jnp.zeros(()), jnp.int32(3), key=KEY)
    space = env.observation_space
    assert ts.obs.dtype == jnp.uint8 and ts.obs.shape == space.shape == (4, 4, 8) and space.dtype == jnp.uint8
    np.testing.assert_array_equal(ts.obs[..., 3:], np.broadcast_to(np.array([0, 0, 0, 255, 0], np.uint8), (4, 4, 5)))
    _, raw = base.step(jnp.zeros(()), jnp.int32(3), key=KEY)
    as_float = jnp.concatenate([raw.obs / 255.0, jnp.broadcast_to(jax.nn.one_hot(3, 5), (4, 4, 5))], axis=-1)
    for kind in ("flatten", "small_cnn"):
        enc = make_encoder((4, 4, 8), 6, key=jax.random.key(1), kind=kind)
        np.testing.assert_allclose(enc(ts.obs), enc(as_float), rtol=1e-6, atol=1e-6)


class BoolGrid(UInt8Image):
    """A 4×4×3 one-hot-like bool grid (the DMLab mazes' observation type)."""

    @property
    def observation_space(self):
        return E.Box(0.0, 1.0, (4, 4, 3), jnp.bool_)

    def reset(self, *, key):
        return jnp.zeros(()), E.timestep(jnp.zeros((4, 4, 3), bool))

    def step(self, state, action, *, key):
        return state, E.timestep(jax.random.bernoulli(key, 0.5, (4, 4, 3)))


def test_action_concat_keeps_bool_grids_and_encodes_them_as_floats():
    """A bool grid stays bool with a one-hot action (a quarter of float32's rollout memory) and encodes as the
    float grid does; with a continuous action it becomes float32, so actions in [-1, 1] survive."""
    from pobax.agent import make_encoder

    base = BoolGrid(E.Discrete(5))
    env = E.ActionConcat(base)
    _, ts = env.step(jnp.zeros(()), jnp.int32(3), key=KEY)
    space = env.observation_space
    assert ts.obs.dtype == jnp.bool_ and ts.obs.shape == space.shape == (4, 4, 8) and space.dtype == jnp.bool_
    np.testing.assert_array_equal(ts.obs[..., 3:], np.broadcast_to(np.arange(5) == 3, (4, 4, 5)))
    as_float = ts.obs.astype(jnp.float32)
    for kind in ("flatten", "small_cnn"):
        enc = make_encoder((4, 4, 8), 6, key=jax.random.key(1), kind=kind)
        np.testing.assert_array_equal(enc(ts.obs), enc(as_float))
    env = E.ActionConcat(BoolGrid(E.Box(-1.0, 1.0, (2,))))
    _, ts = env.step(jnp.zeros(()), jnp.array([-0.5, 0.75]), key=KEY)
    assert ts.obs.dtype == jnp.float32 == env.observation_space.dtype
    np.testing.assert_allclose(ts.obs[0, 0, 3:], [-0.5, 0.75])


def test_action_concat_appends_the_sampled_or_the_applied_action():
    """A Gaussian policy's sample lies outside [-1, 1]; the robots clip it. `applied` appends what the environment
    applied (clipped to the action space), the default what the agent gave; discrete actions are the same either way."""
    action = jnp.array([-3.5, 0.25, 2.0])
    sampled = E.ActionConcat(UInt8Image(E.Box(-1.0, 1.0, (3,))))
    applied = E.ActionConcat(UInt8Image(E.Box(-1.0, 1.0, (3,))), applied=True)
    np.testing.assert_allclose(sampled.step(jnp.zeros(()), action, key=KEY)[1].obs[0, 0, 3:], [-3.5, 0.25, 2.0])
    np.testing.assert_allclose(applied.step(jnp.zeros(()), action, key=KEY)[1].obs[0, 0, 3:], [-1.0, 0.25, 1.0])
    one_hot = [E.ActionConcat(UInt8Image(E.Discrete(5)), applied=a).step(jnp.zeros(()), jnp.int32(3), key=KEY)[1].obs
               for a in (False, True)]
    np.testing.assert_array_equal(*one_hot)
    # from a training configuration through the registry: the wrapper around Walker-V's robot
    from pobax.agent import TrainConfig, make_env

    for choice in ("sampled", "applied"):
        env = make_env(TrainConfig(env="Walker-V-v0", memory="gru", action_concat=True, previous_action=choice))
        while not isinstance(env, E.ActionConcat):
            env = env.env
        assert env.applied == (choice == "applied") and env.action_space == E.Box(-1.0, 1.0, (6,))
    with pytest.raises(ValueError, match="previous_action must be 'sampled' or 'applied'"):
        E.make("tmaze_5", action_concat=True, previous_action="clipped")


@pytest.mark.slow  # 16 s on 2 cores
def test_pooled_reset_matches_reset_every_step():
    """`AutoReset(pool_size=P)` resets only done environments, P per round, yet gives the same episodes as the
    default (reset everywhere, select): vmapped over envs, nested under a vmap over runs, and unbatched."""
    import pobax.env as E

    base = E.TimeLimit(E.make("rocksample_5_3", wrappers=False), 3)  # episodes of <= 3 steps: many end together
    n, t = 6, 12

    def rollout(env, key):
        k0, k1 = jax.random.split(key)
        s, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k0, n))

        def step(s, k):
            ka, ks = jax.random.split(k)
            a = jax.random.randint(ka, (n,), 0, env.action_space.n)
            s, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(s, a, jax.random.split(ks, n))
            return s, (ts.obs, ts.final_obs, ts.done, ts.reward)

        return jax.lax.scan(step, s, jax.random.split(k1, t))[1]

    keys = jax.random.split(jax.random.key(0), 2)
    outs = {}
    for p in (None, 1, 4):
        env = E.AutoReset(base, pool_size=p)
        outs[p] = jax.jit(jax.vmap(lambda k: rollout(env, k)))(keys)
    done = np.asarray(outs[None][2])
    assert done.sum(axis=-1).max() > 4  # some steps end more episodes than one round of 4 resets
    for p in (1, 4):
        for a, b in zip(jax.tree.leaves(outs[p]), jax.tree.leaves(outs[None])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # unbatched: a real branch on `done`
    one = E.AutoReset(base, pool_size=2)
    s, _ = one.reset(key=jax.random.key(1))
    ref = E.AutoReset(base)
    for i in range(8):
        k = jax.random.key(10 + i)
        a = jnp.asarray(i % 4, jnp.int32)
        (s2, ts2), (s, ts) = ref.step(s, a, key=k), one.step(s, a, key=k)
        for a, b in zip(jax.tree.leaves((s, ts)), jax.tree.leaves((s2, ts2))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="pool_size"):
        E.AutoReset(base, pool_size=0)
    # each environment its own map (the environment batched along the same axis as its state): every row
    # resets, and the reset is kept where done
    maps = [E.TimeLimit(E.make("rocksample_5_3", wrappers=False, rock_positions=m), 3)
            for m in (((0, 0), (2, 3), (4, 1)), ((1, 1), (3, 0), (0, 4)))]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *maps)

    def per_map_rollout(pool):
        def run(key):
            k0, k1 = jax.random.split(key)
            s, _ = jax.vmap(lambda env, k: env.reset(key=k))(stacked, jax.random.split(k0, 2))

            def step(s, k):
                ka, ks = jax.random.split(k)
                a = jax.random.randint(ka, (2,), 0, maps[0].action_space.n)
                s, ts = jax.vmap(lambda env, s, a, k: E.AutoReset(env, pool_size=pool).step(s, a, key=k))(
                    stacked, s, a, jax.random.split(ks, 2))
                return s, (ts.obs, ts.done, ts.reward)

            return jax.lax.scan(step, s, jax.random.split(k1, t))[1]

        return jax.jit(run)(jax.random.key(3))

    pooled, every = per_map_rollout(2), per_map_rollout(None)
    assert np.asarray(every[1]).any()
    for a, b in zip(jax.tree.leaves(pooled), jax.tree.leaves(every)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
