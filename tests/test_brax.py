"""Masked MuJoCo (Brax/MJX): masks against the MJX state, termination vs truncation, jit/vmap, determinism.

MJX compiles are slow on CPU (tens of seconds), so each robot is compiled once: Walker (a paper environment) as
a module-scoped rollout of a few vmapped environments that every Walker test reads (`-m slow`: its compile is 40-50 s
on 2 cores), the other robots as one reset and one step.
"""

import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax")

import pobax.env as E  # noqa: E402
from pobax.agent import paper_preset  # noqa: E402
from pobax.env._brax import ROBOTS, BraxEnv, BraxState, _import_brax  # noqa: E402

# Written out here, not taken from the implementation: (positions, velocities) in Brax's observation.
SIZES = {"Walker": (8, 9), "Hopper": (5, 6), "HalfCheetah": (8, 9), "Ant": (13, 14)}
ACTION_SIZES = {"Walker": 6, "Hopper": 3, "HalfCheetah": 6, "Ant": 8}
PINNED = {"Walker": "mjx-newton-1-4", "Hopper": "mjx-newton-1-4", "HalfCheetah": "mjx-newton-1-4",
          "Ant": "mjx-newton-1-4"}
TIME_LIMIT = 5
NUM_STEPS = 6
# Tests do not need fast programs, they need fast compiles (MJX on CPU takes tens of seconds otherwise).
FAST_COMPILE = dict(xla_backend_optimization_level=0, xla_llvm_disable_expensive_passes=True)


def expected_parts(robot, ps):
    """The documented position and velocity entries, read from the MJX state (`ps` = pipeline_state)."""
    q, qd = ps.q, ps.qd
    if robot in ("Walker", "Hopper"):
        # torso height (MuJoCo's xpos z of the torso), pitch and joint angles; velocities clipped to ±10.
        return jnp.concatenate([ps.x.pos[0, 2:3], q[2:]]), jnp.clip(qd, -10.0, 10.0)
    if robot == "HalfCheetah":
        return q[1:], qd  # rootz, pitch, six joints; all of qvel
    return q[2:], qd  # Ant: torso z, quaternion, eight joints; all of qvel


def unhealthy(robot, q):
    """A pose that Brax's health check rejects (HalfCheetah has none: it never terminates)."""
    if robot == "Walker":
        return q.at[2].set(1.5)  # torso pitch outside (-1, 1)
    if robot == "Hopper":
        return q.at[2].set(0.5)  # torso pitch outside (-0.2, 0.2)
    if robot == "Ant":
        return q.at[2].add(1.0)  # torso z above 1.0
    return q.at[2].set(1.5)


def with_pose(brax_state, i, q):
    """`brax_state` (batched) with environment `i` moved to the pose `q`."""
    ps = brax_state.pipeline_state
    ps = ps.replace(q=ps.q.at[i].set(q), qpos=ps.qpos.at[i].set(q))
    return brax_state.replace(pipeline_state=ps)


def check_masks(robot, inner):
    """Every mask and observability of the (batched) Brax states `inner` against the MJX state."""
    n_pos, n_vel = SIZES[robot]
    batch = inner.obs.shape[:-1]
    expected = lambda ps: expected_parts(robot, ps)  # noqa: E731
    for _ in batch:
        expected = jax.vmap(expected)
    pos, vel = expected(inner.pipeline_state)
    assert pos.shape[-1] == n_pos and vel.shape[-1] == n_vel
    full = jnp.concatenate([pos, vel], -1)
    if robot in ("Walker", "Hopper"):
        # The height is 1.25 + rootz, up to the one physics substep by which MJX's kinematics lag qpos.
        np.testing.assert_allclose(pos[..., 0], 1.25 + inner.pipeline_state.q[..., 1], atol=0.02)
    # Brax's own observation is positions then velocities: the full view is Brax's observation.
    np.testing.assert_allclose(inner.obs, full, rtol=1e-6, atol=1e-6)
    for mask, observability, want in [
        ("P", "partial", pos),
        ("V", "partial", vel),
        ("F", "partial", full),
        ("P", "full", full),
        ("V", "full", full),
    ]:
        view = BraxEnv(robot, mask, observability)
        observe = view.observe
        for _ in batch:
            observe = jax.vmap(observe)
        got = observe(BraxState(inner))
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6, err_msg=f"{robot}-{mask} {observability}")
        assert got.shape[-1] == view.observation_space.shape[0] == len(view.observation_names)
    return pos, vel


# ---- Walker, the paper's environment: a rollout through a small TimeLimit -------------------------------------


def walker_rollout(env):
    """Four environments: 0 starts in an unhealthy pose; 1 and 2 share a key, 1 gets actions 3x outside the
    box and 2 the same actions clipped; 3 is an ordinary episode. No auto-reset: episodes run on past their
    end, so the flags after it show what `TimeLimit` does with them."""

    def run(key):
        k_reset, k_act = jax.random.split(key)
        keys = jax.random.split(k_reset, 4)
        keys = keys.at[2].set(keys[1])
        state, ts0 = jax.vmap(lambda k: env.reset(key=k))(keys)
        inner = with_pose(state.env_state.inner, 0, unhealthy("Walker", state.env_state.inner.pipeline_state.qpos[0]))
        state = eqx.tree_at(lambda s: s.env_state.inner, state, inner)
        raw = 3.0 * jax.random.uniform(k_act, (NUM_STEPS, env.action_space.shape[0]), minval=-1.0, maxval=1.0)
        actions = jnp.stack([raw, raw, jnp.clip(raw, -1.0, 1.0), raw], axis=1)

        def body(state, a):
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, a, keys)
            return state, (state, ts)

        _, (states, tss) = jax.lax.scan(body, state, actions)
        return ts0, states, tss

    return jax.jit(run, compiler_options=FAST_COMPILE)


@pytest.fixture(scope="module")
def walker():
    env = E.TimeLimit(BraxEnv("Walker", "V"), TIME_LIMIT)
    run = walker_rollout(env)
    key = jax.random.PRNGKey(0)  # raw keys: the test gives two environments the same key
    return env, run, run(key)


@pytest.mark.slow  # (the module's Walker rollout: 40-50 s of MJX compile on 2 cores)
def test_walker_masks_along_rollout(walker):
    _, _, (ts0, states, tss) = walker
    _, vel = check_masks("Walker", states.env_state.inner)
    # What the agent saw at every step is exactly the velocity part of the state it is in.
    np.testing.assert_allclose(tss.obs, vel, rtol=1e-6, atol=1e-6)
    assert ts0.obs.shape == (4, SIZES["Walker"][1]) and ts0.obs.dtype == jnp.float32
    assert tss.obs.shape == (NUM_STEPS, 4, SIZES["Walker"][1])


@pytest.mark.slow  # (the module's Walker rollout: 40-50 s of MJX compile on 2 cores)
def test_walker_termination_and_truncation(walker):
    _, _, (_, _, tss) = walker
    term, trunc = np.asarray(tss.terminated), np.asarray(tss.truncated)
    assert tss.reward.dtype == jnp.float32 and term.dtype == bool and trunc.dtype == bool
    assert not np.any(term & trunc)
    # The unhealthy start ends at once, as a termination (Brax's done), never as a truncation.
    assert term[0, 0] and not trunc[:, 0].any()
    # The others stand for the few steps of the test: the time limit cuts them, from step TIME_LIMIT on.
    assert not term[:, 1:].any()
    steps = np.arange(1, NUM_STEPS + 1)
    for i in (1, 2, 3):
        np.testing.assert_array_equal(trunc[:, i], steps >= TIME_LIMIT)
    assert np.all(np.isfinite(tss.reward))


@pytest.mark.slow  # (the module's Walker rollout: 40-50 s of MJX compile on 2 cores)
def test_walker_actions_are_clipped(walker):
    _, _, (_, _, tss) = walker
    np.testing.assert_array_equal(tss.obs[:, 1], tss.obs[:, 2])
    np.testing.assert_array_equal(tss.reward[:, 1], tss.reward[:, 2])
    assert not np.allclose(tss.obs[:, 1], tss.obs[:, 3])  # a different key is a different episode


@pytest.mark.slow  # (the module's Walker rollout: 40-50 s of MJX compile on 2 cores)
def test_walker_deterministic(walker):
    _, run, (_, _, tss) = walker
    _, _, again = run(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(again.obs, tss.obs)
    np.testing.assert_array_equal(again.reward, tss.reward)
    _, _, other = run(jax.random.PRNGKey(1))
    assert not np.allclose(other.obs, tss.obs)


# ---- The other robots: one compile each of a reset and one step --------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["Hopper", "HalfCheetah", "Ant"])
def test_masks_and_termination(robot):
    env = BraxEnv(robot, "P")

    def run(keys):
        state0, ts0 = jax.vmap(lambda k: env.reset(key=k))(keys)
        inner = with_pose(state0.inner, 0, unhealthy(robot, state0.inner.pipeline_state.qpos[0]))
        actions = jnp.ones((2, env.action_space.shape[0]))
        state1, ts1 = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(BraxState(inner), actions, keys)
        return state0, ts0, state1, ts1

    state0, ts0, state1, ts1 = jax.jit(run, compiler_options=FAST_COMPILE)(jax.random.split(jax.random.key(4), 2))
    for state, ts in [(state0, ts0), (state1, ts1)]:
        pos, _ = check_masks(robot, state.inner)
        np.testing.assert_allclose(ts.obs, pos, rtol=1e-6, atol=1e-6)
    assert ts1.reward.dtype == jnp.float32 and not ts1.truncated.any()
    # Brax's done is the termination: the unhealthy start falls at once; HalfCheetah never terminates.
    assert ts1.terminated.tolist() == ([False, False] if robot == "HalfCheetah" else [True, False])


def test_state_types_stable_between_reset_and_step():
    # Brax returns weakly typed leaves after `step` (Ant's constant healthy reward): cast, so a jitted step
    # compiles once and scan carries keep their types.
    env = BraxEnv("Ant", "V")
    key = jax.random.key(0)

    def types(tree):
        return jax.tree.map(lambda x: (x.shape, x.dtype, x.weak_type), tree)

    s0, ts0 = jax.eval_shape(lambda k: env.reset(key=k), key)
    s1, ts1 = jax.eval_shape(lambda s, k: env.step(s, jnp.zeros(8), key=k), s0, key)
    assert types(s0) == types(s1)
    assert types(ts0) == types(ts1)


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_spaces_per_id_and_observability(robot):
    n_pos, n_vel = SIZES[robot]
    for mask, partial in [("F", n_pos + n_vel), ("P", n_pos), ("V", n_vel)]:
        name = f"{robot}-{mask}-v0"
        for observability, size in [("partial", partial), ("full", n_pos + n_vel)]:
            env = E.make(name, observability)
            assert env.observation_space.shape == (size,), (name, observability)
            assert env.action_space == E.Box(-1.0, 1.0, (ACTION_SIZES[robot],))
            assert env.max_steps_in_episode == 1000
            assert env.unwrapped.physics == PINNED[robot]
        concat = E.make(name, action_concat=True)
        assert concat.observation_space.shape == (partial + ACTION_SIZES[robot],)


def test_registry_metadata_and_errors():
    for name in ("Walker-V-v0", "HalfCheetah-V-v0"):
        assert name in E.registered_names()
        s = E.spec(name)
        assert s.categories == ("moment features",)
        assert s.recommended["hidden_size"] == 256 and s.recommended["total_steps"] == 50_000_000
        assert s.recommended["normalize_obs"] and s.recommended["normalize_reward"]  # ours, not the paper's
        assert set(s.best) == {"full", "memoryless", "gru", "trxl", "ld"}
        # No previous action for any agent (the release's never see it); the paper's tables give the memory agents one.
        assert not any(best.get("action_concat", False) for best in s.best.values())
        assert paper_preset(name, "gru", original=True)["action_concat"]
        assert not paper_preset(name, "gru").get("action_concat", False)
    assert E.spec("Walker-V-v0").best["trxl"]["lr"] == 2.5e-5
    assert E.spec("Walker-V-v0").best["full"] == dict(lr=2.5e-4, lambda0=0.9)
    # HalfCheetah's ceiling: the GRU row's settings on F (the paper's λ0 0.1 row learned far more slowly here).
    assert E.spec("HalfCheetah-V-v0").best["full"] == E.spec("HalfCheetah-V-v0").best["gru"]
    # no paper table: Walker-V's (a discrepancy loss, a GRU ceiling)
    for name in ("Ant-V-v0", "Hopper-V-v0", "Walker-P-v0"):
        assert E.spec(name).best == E.spec("Walker-V-v0").best and E.spec(name).ceiling_memory == "gru"
    assert E.spec("Ant-V-v0").recommended["embed_size"] == 96
    assert E.spec("HalfCheetah-V-v0").best["ld"] == dict(
        lr=2.5e-5, lambda0=0.95, lambda1=0.7, ld_weight=0.25
    )
    with pytest.raises(E.UnknownEnvironmentError, match="Known environments"):
        E.make("Walker-X-v0")
    with pytest.raises(ValueError, match="observabilit"):
        E.make("Walker-V-v0", "perfect_memory")
    with pytest.raises(ValueError, match="mjx-newton-1-4"):
        E.make("Walker-V-v0", physics="fast-please")
    # Two makes of one ID are equal environments (one jit cache entry).
    a, b = E.make("Walker-V-v0"), E.make("Walker-V-v0")
    assert jax.tree.structure(a) == jax.tree.structure(b)


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_physics_is_pinned(robot):
    from mujoco import mjx

    env = E.make(f"{robot}-V-v0").unwrapped
    assert env.physics == PINNED[robot]
    opt = env.brax_env.sys.opt
    assert env.brax_env.backend == "mjx" and opt.solver == mjx.SolverType.NEWTON
    assert (opt.iterations, opt.ls_iterations) == (1, 4)
    euler_damping = not int(opt.disableflags) & int(mjx.DisableBit.EULERDAMP)
    assert not euler_damping  # every robot, HalfCheetah too (its damped setting went NaN)
    damped = BraxEnv(robot, "V", physics="mjx-newton-1-4-damp").brax_env.sys.opt
    assert not int(damped.disableflags) & int(mjx.DisableBit.EULERDAMP)
    # An explicit physics setting is honoured and is a different environment.
    shipped = BraxEnv(robot, "V", physics="mjx")
    assert shipped.brax_env.sys.opt.ls_iterations == (4 if robot == "Ant" else 50)
    assert jax.tree.structure(shipped) != jax.tree.structure(env)


def test_missing_brax_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "brax", None)
    monkeypatch.setitem(sys.modules, "brax.envs", None)
    with pytest.raises(ImportError, match=r'pip install "pobax-bench\[mujoco\]"'):
        _import_brax()


@pytest.mark.slow
def test_original_mask_layout():
    # The release's HalfCheetah masks (docs/parity.md): V shows four joint angles and their rates, not the torso's
    # velocity; P the rest. Walker's are pobax's; other robots were not compared and are refused.
    full = BraxEnv("HalfCheetah", "F")
    v = E.make("HalfCheetah-V-v0", mask_layout="original").unwrapped
    p = BraxEnv("HalfCheetah", "P", mask_layout="original")
    assert v.observation_names == ("bfoot", "fthigh", "fshin", "ffoot",
                                   "bfoot_vel", "fthigh_vel", "fshin_vel", "ffoot_vel")
    assert p.observation_names == ("torso_z", "torso_pitch", "bthigh", "bshin",
                                   "torso_vx", "torso_vz", "torso_vpitch", "bthigh_vel", "bshin_vel")
    assert v.observation_space.shape == (8,) and p.observation_space.shape == (9,)
    assert sorted(v.visible + p.visible) == list(range(17))  # the two masks split the observation
    assert BraxEnv("HalfCheetah", "V", "full", mask_layout="original").visible == full.visible
    assert BraxEnv("Walker", "V", mask_layout="original").visible == BraxEnv("Walker", "V").visible
    state, _ = jax.jit(lambda k: full.reset(key=k), compiler_options=FAST_COMPILE)(jax.random.key(0))
    seen = np.asarray(state.inner.obs)
    np.testing.assert_array_equal(v.observe(state), seen[[4, 5, 6, 7, 13, 14, 15, 16]])
    np.testing.assert_array_equal(BraxEnv("HalfCheetah", "V").observe(state), seen[8:])
    with pytest.raises(ValueError, match="known for HalfCheetah, Walker only"):
        BraxEnv("Ant", "V", mask_layout="original")
    with pytest.raises(ValueError, match="mask_layout"):
        BraxEnv("Walker", "V", mask_layout="gym")
