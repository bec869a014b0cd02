import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pobax.env as E
from pobax.env import TMaze, TMazeState

UP, RIGHT, DOWN, LEFT = 0, 1, 2, 3
KEY = jax.random.key(0)


def state(pos, goal_up=True):
    return TMazeState(pos=jnp.asarray(pos, jnp.int32), goal_up=jnp.asarray(goal_up))


def step(env, s, a):
    return env.step(s, jnp.asarray(a, jnp.int32), key=KEY)


@pytest.mark.parametrize("goal_up", [True, False])
def test_start_cell_transitions(goal_up):
    env = TMaze(length=3)
    cue = [1.0, 0.0] if goal_up else [0.0, 1.0]
    s0 = state(0, goal_up)
    np.testing.assert_array_equal(env.observe(s0), cue + [0.0, 0.0])
    for a, pos in [(UP, 0), (DOWN, 0), (LEFT, 0), (RIGHT, 1)]:
        s1, ts = step(env, s0, a)
        assert int(s1.pos) == pos
        assert float(ts.reward) == 0.0 and not ts.terminated and not ts.truncated
    _, ts = step(env, s0, RIGHT)
    np.testing.assert_array_equal(ts.obs, [0.0, 0.0, 1.0, 0.0])  # the cue is gone in the hallway


def test_corridor_transitions():
    env = TMaze(length=3)
    s = state(2)
    for a, pos in [(UP, 2), (DOWN, 2), (LEFT, 1), (RIGHT, 3)]:
        s1, ts = step(env, s, a)
        assert int(s1.pos) == pos and float(ts.reward) == 0.0 and not ts.terminated
    _, ts = step(env, state(3), RIGHT)  # last hallway cell → junction
    np.testing.assert_array_equal(ts.obs, [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("goal_up", [True, False])
def test_junction_transitions(goal_up):
    env = TMaze(length=3)
    j = state(4, goal_up)
    _, ts_up = step(env, j, UP)
    _, ts_down = step(env, j, DOWN)
    assert bool(ts_up.terminated) and bool(ts_down.terminated)
    assert float(ts_up.reward) == pytest.approx(4.0 if goal_up else -0.1)
    assert float(ts_down.reward) == pytest.approx(-0.1 if goal_up else 4.0)
    s, ts = step(env, j, RIGHT)  # wall
    assert int(s.pos) == 4 and not ts.terminated and float(ts.reward) == 0.0
    s, ts = step(env, j, LEFT)
    assert int(s.pos) == 3 and not ts.terminated


def test_full_observability_shows_cue_everywhere():
    env = TMaze(length=3, observability="full")
    np.testing.assert_array_equal(env.observe(state(2, True)), [1.0, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(env.observe(state(4, False)), [0.0, 1.0, 0.0, 1.0])
    np.testing.assert_array_equal(env.observe(state(0, False)), [0.0, 1.0, 0.0, 0.0])


def test_optimal_policy_earns_reference_return():
    env = E.make("tmaze_10")
    s, ts = env.reset(key=jax.random.key(3))
    goal_up = bool(ts.obs[0] == 1.0)
    ret, t = 0.0, 0
    for a in [RIGHT] * 11 + [UP if goal_up else DOWN]:
        s, ts = env.step(s, jnp.int32(a), key=jax.random.key(t))
        ret += env.gamma**t * float(ts.reward)
        t += 1
    assert bool(ts.terminated)
    assert ret == pytest.approx(E.spec("tmaze_10").reference()["optimal_discounted_return"], rel=1e-5)
    assert ret == pytest.approx(3.5814, abs=1e-4)


def test_reset_goal_is_balanced_and_cue_visible():
    env = TMaze(length=10)
    _, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(KEY, 4000))
    up = np.asarray(ts.obs[:, 0])
    np.testing.assert_array_equal(up + np.asarray(ts.obs[:, 1]), 1.0)  # exactly one cue bit at the start
    assert 0.45 < up.mean() < 0.55


def test_time_limit_truncates_at_1000():
    env = E.make("tmaze_10")
    s, _ = env.reset(key=KEY)

    def body(s, _):
        s, ts = env.step(s, jnp.int32(UP), key=KEY)  # never reaches the junction
        return s, (ts.truncated, ts.terminated)

    _, (trunc, term) = jax.lax.scan(body, s, None, length=2001)
    trunc = np.asarray(trunc)
    assert np.flatnonzero(trunc).tolist() == [999, 1999]
    assert not np.asarray(term).any()


def test_jit_vmap_determinism():
    env = E.make("tmaze_10", action_concat=True)

    @jax.jit
    def run(key):
        s, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(key, 8))

        def body(c, k):
            s, ts = c
            a = jax.random.randint(k, (8,), 0, 4)
            s, ts = jax.vmap(lambda s_, a_, k_: env.step(s_, a_, key=k_))(s, a, jax.random.split(k, 8))
            return (s, ts), ts.reward

        return jax.lax.scan(body, (s, ts), jax.random.split(key, 200))[1]

    a, b, c = run(jax.random.key(1)), run(jax.random.key(1)), run(jax.random.key(2))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (200, 8)
    assert not np.array_equal(a, c) or np.all(a == 0)


def test_registry_errors():
    with pytest.raises(E.UnknownEnvironmentError, match="Did you mean 'tmaze_10'"):
        E.make("tmaze10")
    with pytest.raises(ValueError, match="has no observability 'perfect_memory'; it has: partial, full"):
        E.make("tmaze_10", "perfect_memory")
    with pytest.raises(ValueError, match=r"hallway length in \[1, 2\*\*31 - 3\]"):
        E.make("tmaze_0")
    spec = E.spec("tmaze_10")
    assert spec.recommended["hidden_size"] == 32
    assert spec.best["gru"]["lr"] == 2.5e-3
