"""No-inventory Crafter (`craftax_pixels`): observations, the inventory crop, the pool auto-reset, achievements,
texture cache location, and a PPO run.

Compiling Craftax's step and world generation takes about a minute on a CPU, so the module shares one compiled
rollout (`rollout` fixture) between the tests of the observations (~1-3 min to compile on a busy 2-core machine);
those, the bit-for-bit comparison with `AutoReset` (three more programs) and the PPO run (one training program,
minutes to compile) are marked `slow`.
"""

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("craftax")

import pobax  # noqa: E402
from pobax.env import AutoReset, TimeLimit  # noqa: E402
from pobax.env._craftax import (  # noqa: E402
    ACHIEVEMENT_NAMES,
    DEFAULT_MAX_TIMESTEPS,
    NUM_ACTIONS,
    PIXEL_SHAPE,
    SYMBOLIC_SIZE,
    CraftaxNoInventory,
    pixel_renderer,
)

N, T, POOL, MAX_T = 4, 7, 2, 5  # 4 envs, 7 steps, worlds generated 2 at a time, Craftax time limit 5


def _fingerprint(craftax_state):
    """A per-world number: the map weighted by position (differs between generated worlds)."""
    m = craftax_state.map.astype(jnp.int32)
    w = jnp.arange(m[0].size, dtype=jnp.int32).reshape(m.shape[-3:]) % 9973
    return jnp.sum(m * jnp.broadcast_to(w, m.shape), axis=(-3, -2, -1))


def _rollout(env, key, kill):
    """`N` envs: reset, kill env 0 (health -1: it dies on its first step), then `T` random steps."""
    k_reset, k_steps = jax.random.split(key)
    s, ts0 = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_reset, N))
    cs = s.env_state
    cs = eqx.tree_at(lambda c: c.player_health, cs, jnp.where(kill, -1, cs.player_health).astype(cs.player_health.dtype))
    s = eqx.tree_at(lambda x: x.env_state, s, cs)

    def body(s, k):
        k_act, k_env = jax.random.split(k)
        a = jax.random.randint(k_act, (N,), 0, NUM_ACTIONS)
        s, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(s, a, jax.random.split(k_env, N))
        return s, dict(ts=ts, state=s.env_state, fp=_fingerprint(s.env_state))

    _, out = jax.lax.scan(body, s, jax.random.split(k_steps, T))
    return dict(out, ts0=ts0, fp0=_fingerprint(cs))


def _is_key(x):
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _np(tree):
    """Leaves as NumPy arrays (PRNG keys stay JAX key arrays)."""
    return jax.tree.map(lambda x: x if _is_key(x) else np.asarray(x), tree)


def _raw(tree):
    return jax.tree.map(lambda x: np.asarray(jax.random.key_data(x)) if _is_key(x) else np.asarray(x), tree)


@pytest.fixture(scope="module")
def env():
    # The registry's stack, with the Craftax time limit cut to MAX_T and worlds generated POOL at a time.
    e = pobax.env.make("craftax_pixels", "partial", max_timesteps=MAX_T)
    assert isinstance(e, AutoReset) and e.pool_size == 8
    return dataclasses.replace(e, pool_size=POOL)


@pytest.fixture(scope="module")
def run(env):
    return jax.jit(lambda key, kill: _rollout(env, key, kill))


@pytest.fixture(scope="module")
def rollout(run):
    kill = jnp.arange(N) == 0
    return _np(run(jax.random.key(0), kill))


@pytest.fixture(scope="module")
def bare():
    return pobax.env.make("craftax_pixels", "partial", wrappers=False)


# ---------------------------------------------------------------------------------------------------------------
# Registry and constants (no compilation)


def test_registry_entry():
    sp = pobax.env.spec("craftax_pixels")
    assert sp.observabilities == ("partial", "full")
    assert sp.family.max_steps == DEFAULT_MAX_TIMESTEPS
    assert sp.family.extra == "craftax"
    assert sp.recommended == dict(hidden_size=512, num_envs=256, total_steps=500_000_000, embed_size=220,
                                  entropy_coeff=0.01)
    assert sp.best["memoryless"] == dict(lr=2.5e-5, lambda0=0.95)
    assert sp.best["ld"] == dict(lr=2.5e-4, lambda0=0.1, lambda1=0.95, ld_weight=0.25, action_concat=True)
    env = pobax.env.make("craftax_pixels", "partial")
    assert isinstance(env, AutoReset) and env.pool_size == 8
    assert env.action_space.n == 43
    assert env.observation_space.shape == (27, 33, 3) and env.observation_space.dtype == jnp.uint8
    assert env.max_steps_in_episode == DEFAULT_MAX_TIMESTEPS
    full = pobax.env.make("craftax_pixels", "full")
    assert full.observation_space.shape == (8268,)
    with pytest.raises(ValueError):
        pobax.env.make("craftax_pixels", "perfect_memory")


def test_constants_match_craftax():
    from craftax.craftax.constants import INVENTORY_OBS_HEIGHT, OBS_DIM, Achievement, Action
    from craftax.craftax.craftax_state import EnvParams

    assert ACHIEVEMENT_NAMES == tuple(a.name.lower() for a in Achievement)
    assert len(ACHIEVEMENT_NAMES) == len(Achievement) == 67
    assert NUM_ACTIONS == len(Action) == 43
    assert DEFAULT_MAX_TIMESTEPS == EnvParams().max_timesteps
    assert PIXEL_SHAPE == (OBS_DIM[0] * 3, OBS_DIM[1] * 3, 3) and INVENTORY_OBS_HEIGHT == 4


def test_pobax_import_does_not_import_craftax():
    code = "import sys, pobax, pobax.env; assert not [m for m in sys.modules if m.startswith('craftax')]"
    subprocess.run([sys.executable, "-c", code], check=True, env=dict(os.environ, JAX_PLATFORMS="cpu"))


@pytest.mark.slow
def test_texture_cache_outside_package(tmp_path):
    """Building the environment in a fresh process, with an empty cache, writes nothing into (a copy of) the
    craftax package and puts the 3 px textures in POBAX_CACHE_DIR."""
    import craftax

    pkg = Path(craftax.__file__).parent
    site = tmp_path / "site"
    shutil.copytree(pkg, site / "craftax", ignore=shutil.ignore_patterns("__pycache__"))

    def listing():
        return sorted((str(p.relative_to(site)), p.stat().st_size, p.stat().st_mtime_ns) for p in site.rglob("*"))

    before = listing()
    cache = tmp_path / "cache"
    code = (
        "import jax, craftax, pobax\n"
        f"assert craftax.__file__.startswith({str(site)!r}), craftax.__file__\n"
        "from pobax.env._craftax import CraftaxNoInventory, texture_cache_file\n"
        "env = CraftaxNoInventory('partial')\n"
        "s, ts = jax.eval_shape(lambda k: env.reset(key=k), jax.random.key(0))\n"
        "assert ts.obs.shape == (27, 33, 3)\n"
        "print(texture_cache_file())\n"
    )
    environ = dict(os.environ, JAX_PLATFORMS="cpu", POBAX_CACHE_DIR=str(cache), PYTHONDONTWRITEBYTECODE="1",
                   PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], check=True, env=environ, capture_output=True, text=True)
    assert listing() == before
    assert not (site / "craftax" / "craftax" / "assets" / "texture_cache.pbz2").exists()
    cached = Path(out.stdout.strip().splitlines()[-1])
    assert cached.parent == cache and cached.exists()


def test_renderer_patch_is_scoped():
    from craftax.craftax import constants, renderer

    pixel_renderer(3)
    assert renderer.load_all_textures is constants.load_all_textures


# ---------------------------------------------------------------------------------------------------------------
# The shared rollout: shapes, the pool reset, achievements


@pytest.mark.slow
def test_shapes_and_dtypes(rollout):
    ts = rollout["ts"]
    assert ts.obs.shape == (T, N, 27, 33, 3) and ts.obs.dtype == np.uint8
    assert ts.final_obs.shape == ts.obs.shape and ts.final_obs.dtype == np.uint8
    assert ts.reward.shape == (T, N) and ts.reward.dtype == np.float32
    assert ts.terminated.dtype == bool and ts.truncated.dtype == bool
    assert set(ts.info) == {"achievements"} and set(rollout["ts0"].info) == {"achievements"}
    ach = ts.info["achievements"]
    assert ach.shape == (T, N, 67) and ach.dtype == np.float32
    assert np.isin(ach, [0.0, 1.0]).all()
    assert rollout["ts0"].obs.shape == (N, 27, 33, 3)
    assert ts.obs.max() > 0 and ts.obs.std() > 0  # a real picture


@pytest.mark.slow
def test_obs_is_the_render_of_the_state(rollout, bare):
    """Every observation (including the first one of a new episode) is the 3 px map of the returned state."""
    states = rollout["state"]
    obs = jax.jit(jax.vmap(jax.vmap(bare._obs)))(states)
    np.testing.assert_array_equal(np.asarray(obs), rollout["ts"].obs)


@pytest.mark.slow
def test_episode_ends_and_same_step_reset(rollout):
    ts, st, fp = rollout["ts"], rollout["state"], rollout["fp"]
    term, trunc = ts.terminated, ts.truncated
    # Env 0 dies on its first step; its new episode truncates MAX_T steps later. Envs 1-3 truncate together.
    expected_term = np.zeros((T, N), bool)
    expected_term[0, 0] = True
    expected_trunc = np.zeros((T, N), bool)
    expected_trunc[MAX_T - 1, 1:] = True
    expected_trunc[MAX_T, 0] = True
    np.testing.assert_array_equal(term, expected_term)
    np.testing.assert_array_equal(trunc, expected_trunc)
    done = term | trunc
    # Same-step reset: the returned state is a new episode (timestep 0, no achievements, full health).
    assert (st.timestep[done] == 0).all()
    assert (st.timestep[~done] > 0).all()
    assert (st.achievements[done] == 0).all()
    assert (st.player_health[done] > 0).all()
    # final_obs is the obs of the ended episode; obs is the new world's; elsewhere they coincide.
    np.testing.assert_array_equal(ts.final_obs[~done], ts.obs[~done])
    assert all((ts.final_obs[t, i] != ts.obs[t, i]).any() for t, i in zip(*np.nonzero(done)))
    # World fingerprints: constant within an episode, new at each reset.
    prev = np.concatenate([rollout["fp0"][None], fp[:-1]])
    np.testing.assert_array_equal(fp[~done], prev[~done])
    assert (fp[done] != prev[done]).all()


@pytest.mark.slow
def test_distinct_fresh_worlds(rollout):
    """Three envs finish on the same step with worlds generated two at a time: all three get distinct, new
    worlds, different from every world seen before."""
    fp, fp0 = rollout["fp"], rollout["fp0"]
    new = fp[MAX_T - 1, 1:]
    assert len(set(new.tolist())) == 3
    seen = set(fp0.tolist()) | set(fp[: MAX_T - 1].ravel().tolist())
    assert not set(new.tolist()) & seen
    assert len(set(fp0.tolist())) == N


@pytest.mark.slow
def test_achievements_info(rollout):
    """`info["achievements"]` are the state's achievements; on the step that ends an episode they are the ended
    episode's (the reset state starts with none)."""
    ts, st = rollout["ts"], rollout["state"]
    done = ts.terminated | ts.truncated
    ach = ts.info["achievements"]
    np.testing.assert_array_equal(ach[~done], st.achievements[~done].astype(np.float32))
    # Monotone within an episode.
    prev = np.concatenate([rollout["ts0"].info["achievements"][None], ach[:-1]])
    starts = np.concatenate([np.zeros((1, N), bool), done[:-1]])
    assert (ach[~starts] >= prev[~starts]).all()


@pytest.mark.slow
def test_deterministic_and_key_dependent(run, rollout):
    kill = jnp.arange(N) == 0
    again = _raw(run(jax.random.key(0), kill))
    for a, b in zip(jax.tree.leaves(again), jax.tree.leaves(_raw(rollout))):
        np.testing.assert_array_equal(a, b)
    other = _np(run(jax.random.key(1), kill))
    assert not set(other["fp0"].tolist()) & set(rollout["fp0"].tolist())


# ---------------------------------------------------------------------------------------------------------------
# The inventory crop and the full observation (render-only programs, quick to compile)


@pytest.mark.slow
def test_inventory_is_cropped(rollout, bare):
    """Two states that differ only in the inventory and intrinsics: Craftax's render at 3 px differs (in the
    inventory rows only), the partial observation does not, and equals the top 27 rows of the render."""
    state = jax.tree.map(lambda x: x[0, 1], rollout["state"])
    other = eqx.tree_at(
        lambda s: (s.inventory.wood, s.inventory.stone, s.inventory.pickaxe, s.player_food, s.player_drink),
        state,
        (jnp.asarray(9, state.inventory.wood.dtype), jnp.asarray(7, state.inventory.stone.dtype),
         jnp.asarray(1, state.inventory.pickaxe.dtype), jnp.asarray(2, state.player_food.dtype),
         jnp.asarray(3, state.player_drink.dtype)),
    )
    full = pobax.env.make("craftax_pixels", "full", wrappers=False)

    @jax.jit
    def views(s):
        return bare.render_full_pixels(s), bare._obs(s), full._obs(s)

    ref_a, obs_a, sym_a = map(np.asarray, views(state))
    ref_b, obs_b, sym_b = map(np.asarray, views(other))
    assert ref_a.shape == (39, 33, 3)
    rows_differ = np.nonzero((ref_a != ref_b).any(axis=(1, 2)))[0]
    assert len(rows_differ) > 0 and rows_differ.min() >= 27  # the inventory strip is rows 27..38
    np.testing.assert_array_equal(obs_a, obs_b)  # would fail if any inventory row were kept
    np.testing.assert_array_equal(obs_a, np.clip(np.round(ref_a[:27]), 0, 255).astype(np.uint8))
    assert (sym_a != sym_b).any()  # the full observation shows the inventory


@pytest.mark.slow
def test_full_observation(rollout):
    full = pobax.env.make("craftax_pixels", "full", wrappers=False)
    sym = np.asarray(jax.jit(jax.vmap(jax.vmap(full._obs)))(rollout["state"]))
    assert sym.shape == (T, N, SYMBOLIC_SIZE) and sym.dtype == np.float32
    assert np.isfinite(sym).all() and sym.min() >= 0.0
    assert full.observation_space.contains(jnp.asarray(sym[0, 0]))
    _, ts = jax.eval_shape(lambda k: full.reset(key=k), jax.random.key(0))
    assert ts.obs.shape == (SYMBOLIC_SIZE,) and ts.info["achievements"].shape == (67,)


# ---------------------------------------------------------------------------------------------------------------
# Bit-for-bit equal to AutoReset (slow: three more Craftax programs)


@pytest.mark.slow
def test_pool_reset_equals_auto_reset():
    """Same keys, same trajectories: `AutoReset(pool_size=1)` (1 world per round, so 3 rounds when 3 envs finish
    together) vs `AutoReset`, vmapped over envs, nested under a vmap over runs, and unbatched."""
    base = TimeLimit(CraftaxNoInventory("partial", max_timesteps=MAX_T), DEFAULT_MAX_TIMESTEPS)
    pool, naive = AutoReset(base, pool_size=1), AutoReset(base)
    kill = jnp.arange(N) == 0
    keys = jax.random.split(jax.random.key(3), 2)

    def obs_and_fp(out):
        return out["ts"].obs, out["ts"].final_obs, out["ts"].done, out["fp"]

    a = jax.jit(jax.vmap(lambda k: obs_and_fp(_rollout(pool, k, kill))))(keys)
    b = jax.jit(jax.vmap(lambda k: obs_and_fp(_rollout(naive, k, kill))))(keys)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert np.asarray(a[2]).sum() == 2 * 5

    def single(env, key):  # one env, no vmap: the reset is a lax.cond
        s, _ = env.reset(key=key)

        def body(s, k):
            s, ts = env.step(s, jnp.int32(0), key=k)
            return s, (ts.obs, ts.done)

        return jax.lax.scan(body, s, jax.random.split(key, MAX_T + 1))[1]

    u = jax.jit(lambda k: (single(pool, k), single(naive, k)))(keys[0])
    (obs_p, done_p), (obs_n, done_n) = u
    np.testing.assert_array_equal(np.asarray(obs_p), np.asarray(obs_n))
    assert np.asarray(done_p)[MAX_T - 1]


# ---------------------------------------------------------------------------------------------------------------
# PPO


@pytest.mark.slow
def test_ppo_logs_achievement_rates_and_trains_every_weight():
    """A GRU agent with the CNN encoder, two updates: each update logs every achievement's success rate (a share of
    the update's finished episodes, in [0, 1]), and every weight array moves from its initialisation."""
    from pobax.agent import Runs, TrainConfig
    from pobax.eval import train

    cfg = TrainConfig(env="craftax_pixels", observability="partial", hidden_size=16, num_envs=2, memory="gru",
                      action_concat=True, num_minibatches=2, num_steps=8, total_steps=2 * 8 * 2, num_seeds=1,
                      num_chunks=1, fast_compile=True)
    r = train(cfg, save=False, progress=False)
    m = r.metrics
    assert len(m) == 2 and list(m.env_step) == [16, 32]
    rates = m[[f"achievement_{n}" for n in ACHIEVEMENT_NAMES]].to_numpy()
    assert ((rates >= 0) & (rates <= 1) | np.isnan(rates)).all()
    before = jax.tree.leaves(eqx.filter(Runs(cfg).init().model, eqx.is_inexact_array))
    after = jax.tree.leaves(eqx.filter(r.state.model, eqx.is_inexact_array))
    assert all(not np.array_equal(b, a) for b, a in zip(before, after))
