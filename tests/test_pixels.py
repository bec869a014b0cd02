"""Pixel MuJoCo (`*_pixels`) and its pure-JAX ray caster.

The renderer is tested on MuJoCo poses computed by MuJoCo's C library (`mj_forward`), which needs no MJX
compile: depth and geom ids against `mujoco.mjx.ray`, every robot visible, tracking. The environment itself
(one HalfCheetah compile, shared) is tested for shapes, dtypes, jit and vmap; PPO with a CNN for a few updates
(memoryless and GRU) is marked `slow` (each run compiles MJX and the learner: minutes on a busy CPU).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax")

import mujoco  # noqa: E402
from mujoco import mjx  # noqa: E402

import pobax.env as E  # noqa: E402
from pobax.env import _raycast as R  # noqa: E402
from pobax.env._brax import PHYSICS_BY_ROBOT, load_brax_env  # noqa: E402
from pobax.env._pixels import TORSO_BODY, PixelBrax, geom_poses, load_scene, save_frame_grid  # noqa: E402

# Tests need fast compiles, not fast programs.
FAST_COMPILE = dict(xla_backend_optimization_level=0, xla_llvm_disable_expensive_passes=True)
ROBOTS = {"halfcheetah_pixels": "HalfCheetah", "ant_pixels": "Ant", "hopper_pixels": "Hopper",
          "walker2d_pixels": "Walker"}
FULL_SIZES = {"HalfCheetah": 17, "Ant": 27, "Hopper": 11, "Walker": 17}  # Brax's observation sizes


def mj_pose(mj_model, seed=0, noise=0.1):
    """MuJoCo (C) data at the initial pose plus joint noise, after `mj_forward`."""
    data = mujoco.MjData(mj_model)
    rng = np.random.default_rng(seed)
    data.qpos[:] = mj_model.qpos0 + noise * rng.standard_normal(mj_model.nq)
    mujoco.mj_forward(mj_model, data)
    return data


def poses(data):
    return (jnp.asarray(data.geom_xpos, jnp.float32), jnp.asarray(data.geom_xmat.reshape(-1, 3, 3), jnp.float32),
            jnp.asarray(data.xpos[TORSO_BODY], jnp.float32))


def scene_of(robot, **kw):
    return load_scene(robot, PHYSICS_BY_ROBOT[robot], 32, **kw)


_render = jax.jit(R.render, static_argnums=0, compiler_options=FAST_COMPILE)
_depth = jax.jit(R.render_depth, static_argnums=0, compiler_options=FAST_COMPILE)


def mjx_rays(mj_model, data, origins, dirs):
    m, d = mjx.put_model(mj_model), mjx.put_data(mj_model, data)

    def one(o, v):
        with jax.numpy_rank_promotion("allow"):
            return mjx.ray(m, d, o, v)

    return jax.jit(jax.vmap(one), compiler_options=FAST_COMPILE)(origins, dirs)


def check_against_mjx(scene, mj_model, data, pick):
    """Depth and geom id of the pixels `pick` (flat indices) agree with `mjx.ray` from the same origin."""
    xpos, xmat, torso = poses(data)
    depth, geom = (np.asarray(a).reshape(-1) for a in _depth(scene, xpos, xmat, torso))
    origin = np.asarray(scene.camera.origin(torso))
    # mjx.ray stops planes at their rendered rectangle; the renderer's floor is infinite: compare inside.
    points = origin + np.where(np.isfinite(depth), depth, 0)[:, None] * scene.camera.ray_directions(32, 32)
    outside = (geom == 0) & np.any(np.abs(points[:, :2]) >= mj_model.geom_size[0, :2], axis=1)
    pick = np.asarray([p for p in pick if not outside[p]])
    dirs = scene.camera.ray_directions(scene.height, scene.width)[pick]
    dist, ids = (np.asarray(a) for a in mjx_rays(mj_model, data, np.tile(origin, (len(pick), 1)), dirs))
    hit = ids >= 0
    np.testing.assert_array_equal(hit, geom[pick] >= 0)
    np.testing.assert_allclose(dist[hit], depth[pick][hit], rtol=1e-4, atol=1e-4)
    assert np.all(dist[~hit] == -1) and np.all(np.isinf(depth[pick][~hit]))
    # The same geom, except at a tie: where two geoms meet with the same surface (e.g. Ant's foot sphere at
    # the end of its shin capsule) both find the same distance and may name either geom.
    differ = ids != geom[pick]
    assert differ.mean() <= 0.1, (ids, geom[pick])
    for i in np.nonzero(differ)[0]:
        assert {ids[i], geom[pick][i]} <= set(np.nonzero(np.asarray(mj_model.geom_bodyid) > 0)[0])


@pytest.mark.parametrize("robot", ["HalfCheetah", "Ant"])
def test_depth_and_geom_ids_agree_with_mjx_ray(robot):
    mj_model = load_brax_env(robot, PHYSICS_BY_ROBOT[robot]).sys.mj_model
    data = mj_pose(mj_model)
    scene = scene_of(robot)
    xpos, xmat, torso = poses(data)
    depth, geom = (np.asarray(a).reshape(-1) for a in _depth(scene, xpos, xmat, torso))
    # Robot pixels, floor pixels inside the plane's rendered rectangle (where mjx.ray stops it) and sky.
    origin = np.asarray(scene.camera.origin(torso))
    points = origin + np.where(np.isfinite(depth), depth, 0)[:, None] * scene.camera.ray_directions(32, 32)
    floor = (geom == 0) & np.all(np.abs(points[:, :2]) < mj_model.geom_size[0, :2], axis=1)
    robot_px, floor_px, sky_px = np.nonzero(geom > 0)[0], np.nonzero(floor)[0], np.nonzero(geom < 0)[0]
    assert len(robot_px) >= 20 and len(floor_px) >= 4  # (Ant's camera looks down: no sky)
    pick = np.concatenate([robot_px[:: max(1, len(robot_px) // 24)], floor_px[:: len(floor_px) // 4][:4],
                           sky_px[:: max(1, len(sky_px) // 4)][:4]])
    check_against_mjx(scene, mj_model, data, pick)


BOX_ELLIPSOID_XML = """
<mujoco>
  <default><geom contype="0" conaffinity="0"/></default>
  <asset><material name="floor" rgba="1 1 1 1"/></asset>  <!-- mjx.ray indexes materials: have one -->
  <worldbody>
    <geom type="plane" size="5 5 0.1" material="floor"/>
    <body pos="0 0 0.6" euler="20 30 40">
      <freejoint/>
      <geom type="box" size="0.3 0.2 0.1" rgba="1 0 0 1"/>
    </body>
    <body pos="0.7 0.2 0.5" euler="-30 10 60">
      <freejoint/>
      <geom type="ellipsoid" size="0.3 0.15 0.2" rgba="0 1 0 1"/>
    </body>
    <body pos="-0.7 -0.1 0.4" euler="0 45 10">
      <freejoint/>
      <geom type="capsule" size="0.08 0.3" rgba="0 0 1 1"/>
      <geom type="sphere" size="0.15" pos="0 0 0.5" rgba="1 1 0 1"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_box_ellipsoid_capsule_sphere_agree_with_mjx_ray():
    mj_model = mujoco.MjModel.from_xml_string(BOX_ELLIPSOID_XML)
    data = mj_pose(mj_model, noise=0.0)
    scene = R.Scene.from_model(mj_model, R.Camera(distance=3.0, azimuth=60.0, elevation=-25.0,
                                                   offset=(0.0, 0.0, 0.4)), 32, 32)
    xpos, xmat, torso = poses(data)
    _, geom = _depth(scene, xpos, xmat, torso)
    geom = np.asarray(geom).reshape(-1)
    for g in range(1, mj_model.ngeom):
        assert np.sum(geom == g) >= 10, f"geom {g} hardly visible"
    check_against_mjx(scene, mj_model, data, np.arange(0, 32 * 32, 3))


def test_unsupported_geom_type_is_refused():
    mj_model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom type="cylinder" size="0.1 0.2"/></worldbody></mujoco>')
    with pytest.raises(NotImplementedError, match="cylinder|unsupported"):
        R.Scene.from_model(mj_model, R.Camera(2.0, 90.0, 0.0))


@pytest.mark.parametrize("robot", list(FULL_SIZES))
def test_every_robot_is_visible(robot, tmp_path):
    """Not an empty scene: the robot covers enough pixels, and hiding it changes the frame (an all-sky or
    all-floor image fails both)."""
    mj_model = load_brax_env(robot, PHYSICS_BY_ROBOT[robot]).sys.mj_model
    data = mj_pose(mj_model, noise=0.05)
    scene = scene_of(robot)
    xpos, xmat, torso = poses(data)
    frame = np.asarray(_render(scene, xpos, xmat, torso))
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8
    _, geom = _depth(scene, xpos, xmat, torso)
    robot_px = int(np.sum(np.asarray(geom) > 0))
    assert robot_px >= 25, (robot, robot_px)
    # The floor is seen too (and for the side views the sky).
    assert np.sum(np.asarray(geom) == 0) >= 100
    assert robot == "Ant" or np.sum(np.asarray(geom) < 0) >= 32
    hidden = xpos.at[1:, 2].add(-100.0)  # robot geoms far below the floor
    empty = np.asarray(_render(scene, hidden, xmat, torso))
    changed = np.any(frame != empty, axis=-1)
    assert changed.sum() >= robot_px  # robot pixels and its shadow
    if robot == "HalfCheetah":  # side view, nothing occluded: every limb is at least a pixel
        assert set(np.unique(np.asarray(geom))) >= set(range(1, mj_model.ngeom))
    save_frame_grid(np.stack([frame, empty]), str(tmp_path / "grid.png"), cols=2)
    assert (tmp_path / "grid.png").stat().st_size > 0


def test_camera_tracks_the_torso():
    """Moving the whole robot by one checker period (1 m along x) leaves the frame unchanged."""
    robot = "HalfCheetah"
    mj_model = load_brax_env(robot, PHYSICS_BY_ROBOT[robot]).sys.mj_model
    xpos, xmat, torso = poses(mj_pose(mj_model))
    shift = jnp.asarray([1.0, 0.0, 0.0])
    moved = xpos.at[1:].add(shift[None])
    a = np.asarray(_render(scene_of(robot), xpos, xmat, torso)).astype(int)
    b = np.asarray(_render(scene_of(robot), moved, xmat, torso + shift)).astype(int)
    assert np.abs(a - b).max() <= 1


@pytest.mark.parametrize("robot", ["HalfCheetah", "Walker"])
def test_positional_geom_poses_agree_with_mujoco(robot):
    """Rendering Brax's positional pipeline (the original's physics): geom poses from its link frames equal
    MuJoCo's `geom_xpos`/`geom_xmat` at the same joint positions (Brax's kinematics; no physics step)."""
    from brax import kinematics

    sys = load_brax_env(robot, "positional").sys
    data = mj_pose(sys.mj_model, seed=1)
    q = jnp.asarray(data.qpos, jnp.float32)
    x, _ = jax.jit(kinematics.forward)(sys, q, jnp.zeros(sys.qd_size()))
    xpos, xmat = geom_poses(sys, x.pos, x.rot)
    np.testing.assert_allclose(np.asarray(xpos), data.geom_xpos, atol=2e-5)
    np.testing.assert_allclose(np.asarray(xmat), data.geom_xmat.reshape(-1, 3, 3), atol=2e-5)


@pytest.mark.slow  # 13 s on 2 cores: two MJX renders
def test_positional_frames_equal_mjx_frames_at_the_same_pose():
    """`physics=positional` renders from Brax's link frames: at reset, where both pipelines put HalfCheetah at the same
    joint positions, its frame is the MJX frame pixel for pixel. An unknown physics setting is refused."""
    frames = []
    for physics in (PHYSICS_BY_ROBOT["HalfCheetah"], "positional"):
        env = E.make("halfcheetah_pixels", "partial", physics=physics, wrappers=False)
        assert env.physics == physics
        _, ts = jax.jit(lambda k, env=env: env.reset(key=k), compiler_options=FAST_COMPILE)(jax.random.key(3))
        frames.append(np.asarray(ts.obs))
    assert frames[0].shape == (32, 32, 3) and frames[0].std() > 10  # a picture, not a blank
    np.testing.assert_array_equal(frames[1], frames[0])
    with pytest.raises(ValueError, match="physics"):
        E.make("halfcheetah_pixels", "partial", physics="euler")


# --- The environment ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(ROBOTS))
@pytest.mark.parametrize("observability", ["partial", "full"])
def test_spaces_and_shapes(name, observability):
    env = E.make(name, observability)
    assert isinstance(env.unwrapped, PixelBrax) and env.max_steps_in_episode == 1000
    space = env.observation_space
    if observability == "partial":
        assert space.shape == (32, 32, 3) and space.dtype == jnp.uint8 and (space.low, space.high) == (0, 255)
    else:
        assert space.shape == (FULL_SIZES[ROBOTS[name]],)
    if name in ("halfcheetah_pixels", "ant_pixels"):  # trace reset and step (no compile)
        bare = E.make(name, observability, wrappers=False)
        state, ts = jax.eval_shape(lambda k: bare.reset(key=k), jax.random.key(0))
        action = jnp.zeros(bare.action_space.shape)
        _, ts2 = jax.eval_shape(lambda s, k: bare.step(s, action, key=k), state, jax.random.key(1))
        for t in (ts, ts2):
            assert t.obs.shape == space.shape and t.obs.dtype == space.dtype
            assert t.reward.shape == () and t.terminated.dtype == jnp.bool_


def test_registry_metadata():
    for name in ("ant_pixels", "halfcheetah_pixels"):
        spec = E.spec(name)
        assert name in E.registered_names()
        assert spec.categories == ("visual occlusion", "moment features") and spec.family.extra == "mujoco"
        assert spec.recommended["hidden_size"] == 512 and spec.recommended["embed_size"] == 220
        assert spec.recommended["total_steps"] == 5_000_000
        assert set(spec.best) == {"full", "memoryless", "gru", "trxl", "ld"}
        assert spec.best["gru"]["action_concat"] and "ld_weight" in spec.best["ld"]
    assert E.spec("ant_pixels").best["ld"] == dict(lr=2.5e-4, lambda0=0.1, lambda1=0.5, ld_weight=0.5,
                                                   action_concat=True)
    assert E.spec("halfcheetah_pixels").best["memoryless"] == dict(lr=2.5e-4, lambda0=0.7)
    # every ceiling (Brax's state) normalises its observations and rewards, the paper's own table did not
    norm = dict(normalize_obs=True, normalize_reward=True)
    assert E.spec("ant_pixels").best["full"] == dict(lr=2.5e-4, lambda0=0.5, **norm)
    assert E.spec("ant_pixels").paper_original["full"] == dict(normalize_obs=False, normalize_reward=False)
    # halfcheetah_pixels's ceiling is HalfCheetah-V's: a GRU on the state with the previous action, λ0 0.9
    assert (E.spec("ant_pixels").ceiling_memory, E.spec("halfcheetah_pixels").ceiling_memory) == ("memoryless", "gru")
    assert E.spec("halfcheetah_pixels").best["full"] == dict(lr=2.5e-4, lambda0=0.9, action_concat=True, **norm)
    assert E.spec("halfcheetah_pixels").paper_original["full"] == dict(lambda0=0.5, action_concat=False,
                                                                      normalize_obs=False, normalize_reward=False)
    # no paper table: only the λ-discrepancy agent's λ1 and β (halfcheetah_pixels'), so that it has a discrepancy loss
    assert E.spec("hopper_pixels").best == E.spec("walker2d_pixels").best == {"ld": dict(lambda1=0.95, ld_weight=0.5),
                                                                             "full": norm}


@pytest.fixture(scope="module")
def cheetah_rollout():
    """Two vmapped HalfCheetah environments: reset and three random steps (one compile for the file)."""
    env = E.make("halfcheetah_pixels", "partial", wrappers=False)

    def run(keys):
        state, ts = jax.vmap(lambda k: env.reset(key=k))(keys)
        states, obs = [state], [ts.obs]
        for i in range(3):
            actions = jax.vmap(lambda k: env.action_space.sample(jax.random.fold_in(k, i)))(keys)
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, actions, keys)
            states.append(state)
            obs.append(ts.obs)
        return states, jnp.stack(obs, axis=1), ts

    states, obs, ts = jax.jit(run, compiler_options=FAST_COMPILE)(jax.random.split(jax.random.key(0), 2))
    return env, states, obs, ts


@pytest.mark.slow
def test_jit_vmap_over_envs(cheetah_rollout):
    env, states, obs, ts = cheetah_rollout
    assert obs.shape == (2, 4, 32, 32, 3) and obs.dtype == jnp.uint8
    assert ts.reward.shape == (2,) and np.all(np.isfinite(np.asarray(ts.reward)))
    obs = np.asarray(obs)
    assert obs.min() < 100 and obs.max() > 150  # not a flat image
    assert np.any(obs[:, 0] != obs[:, -1])  # the robot moved
    # The observation is the render of the state; `full` observes the same state as Brax's state vector.
    full = PixelBrax("HalfCheetah", "full")
    last = states[-1]
    frame = eqx.filter_jit(jax.vmap(env.render))(last)
    np.testing.assert_array_equal(np.asarray(frame), obs[:, -1])
    vec = jax.vmap(full.observe)(last)
    assert vec.shape == (2, 17) and vec.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(vec), np.asarray(last.inner.obs))


def test_render_frames_helper():
    from pobax.env import render_frames

    # T-Maze stands in for a pixel environment: no MJX compile; the scan and shapes are the helper's. By name, or an
    # environment already made (here the one the name makes), with the same frames.
    frames = render_frames("tmaze_5", 3, seed=1)
    assert frames.shape[0] == 3
    np.testing.assert_array_equal(render_frames(E.make("tmaze_5", "partial"), 3, seed=1), frames)
    with pytest.raises(TypeError, match="overrides"):
        render_frames(E.make("tmaze_5", "partial"), 3, image_size=64)


# Each compiles MJX physics, the renderer and a CNN learner (minutes on a 2-core CPU): `-m slow`.
@pytest.mark.slow
@pytest.mark.parametrize("memory", ["memoryless", "gru"])
def test_ppo_trains_every_weight_on_pixels(memory):
    """Two updates from frames: finite losses, and every weight array (CNN, memory, heads) moves from its
    initialisation, so gradients reach the encoder through the rendered observations."""
    from pobax.agent import Runs, TrainConfig
    from pobax.eval import train

    agent = dict(memory=memory) if memory == "memoryless" else dict(memory="gru", action_concat=True)
    cfg = TrainConfig(env="halfcheetah_pixels", hidden_size=16, num_envs=2, num_minibatches=2, num_steps=8,
                      total_steps=2 * 8 * 2, num_seeds=1, num_chunks=1, fast_compile=True, **agent)
    r = train(cfg, save=False, progress=False)
    m = r.metrics
    assert len(m) == 2
    for col in ("pg_loss", "v_loss", "entropy", "approx_kl"):
        assert np.isfinite(m[col]).all(), (memory, col)
    before = jax.tree.leaves(eqx.filter(Runs(cfg).init().model, eqx.is_inexact_array))
    after = jax.tree.leaves(eqx.filter(r.state.model, eqx.is_inexact_array))
    assert all(not np.array_equal(b, a) for b, a in zip(before, after))
