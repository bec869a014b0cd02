"""No-inventory Crafter (`craftax_pixels`, paper appendix "No-inventory Crafter"), built on Craftax.

The game is full Craftax (not Classic): `Craftax-Pixels-v1`'s world generation, game logic, 43 actions,
achievements and reward. Observabilities:

- `partial`: the local map (9 x 11 blocks) rendered by Craftax's own pixel renderer at 3 x 3 pixels per block,
  with the inventory strip (the 4 block rows the renderer draws under the map) removed: a `(27, 33, 3)` uint8
  image in [0, 255]. The agent must remember its items and stats.
- `full`: Craftax's symbolic observation `(8268,)` (float32), which includes the inventory and intrinsics.

Craftax is imported lazily (only when an environment is built), so `import pobax` does not need it.

Textures. Craftax's `load_all_textures` builds textures for 10, 16 and 64 px blocks only and writes its cache
into its own package directory (which crashes on a read-only install). We build the 3 px textures with
Craftax's `load_all_textures_given_size(3)`, cache them under the user cache directory (`$POBAX_CACHE_DIR`,
else `$XDG_CACHE_HOME/pobax`, else `~/.cache/pobax`), and hand them to Craftax's
`make_craftax_pixel_renderer(3)`: while that factory runs (it only looks the textures up), the renderer
module's `load_all_textures` name is pointed at ours. No installed file is touched or written.

Resets. Generating a Craftax world is far more expensive than a step, and the default `AutoReset` (like
Craftax's own auto-reset) generates one for every environment on every step and selects it where an episode
ended. `PoolAutoReset` generates worlds only for the environments that are done; see its docstring.
"""

import functools
import importlib.metadata
import os
import threading
from pathlib import Path
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from ._base import AbstractEnvironment, AbstractWrapper, TimeStep, timestep
from ._registry import EnvFamily
from ._spaces import Box, Discrete

# Craftax's `Achievement` enum, in order (lower case). Craftax 1.6 has 67 (the paper's text says 65); a test
# checks this tuple against the installed enum.
ACHIEVEMENT_NAMES: tuple[str, ...] = (
    "collect_wood", "place_table", "eat_cow", "collect_sapling", "collect_drink", "make_wood_pickaxe",
    "make_wood_sword", "place_plant", "defeat_zombie", "collect_stone", "place_stone", "eat_plant",
    "defeat_skeleton", "make_stone_pickaxe", "make_stone_sword", "wake_up", "place_furnace", "collect_coal",
    "collect_iron", "collect_diamond", "make_iron_pickaxe", "make_iron_sword", "make_arrow", "make_torch",
    "place_torch", "collect_sapphire", "collect_ruby", "make_diamond_pickaxe", "make_diamond_sword",
    "make_iron_armour", "make_diamond_armour", "enter_gnomish_mines", "enter_dungeon", "enter_sewers",
    "enter_vault", "enter_troll_mines", "enter_fire_realm", "enter_ice_realm", "enter_graveyard",
    "defeat_gnome_warrior", "defeat_gnome_archer", "defeat_orc_solider", "defeat_orc_mage", "defeat_lizard",
    "defeat_kobold", "defeat_knight", "defeat_archer", "defeat_troll", "defeat_deep_thing", "defeat_pigman",
    "defeat_fire_elemental", "defeat_frost_troll", "defeat_ice_elemental", "damage_necromancer",
    "defeat_necromancer", "eat_bat", "eat_snail", "find_bow", "fire_bow", "learn_fireball", "cast_fireball",
    "learn_iceball", "cast_iceball", "open_chest", "drink_potion", "enchant_sword", "enchant_armour",
)
NUM_ACTIONS = 43
# Craftax's `EnvParams().max_timesteps` (full Craftax; Craftax-Classic uses 10000). A test checks it.
DEFAULT_MAX_TIMESTEPS = 100_000
BLOCK_PIXELS = 3
MAP_BLOCKS = (9, 11)  # Craftax's OBS_DIM: rows x columns of blocks around the player
PIXEL_SHAPE = (MAP_BLOCKS[0] * BLOCK_PIXELS, MAP_BLOCKS[1] * BLOCK_PIXELS, 3)  # (27, 33, 3)
SYMBOLIC_SIZE = 8268


def cache_dir() -> Path:
    """Where pobax caches derived files: `$POBAX_CACHE_DIR`, else `$XDG_CACHE_HOME/pobax`, else
    `~/.cache/pobax`."""
    if os.environ.get("POBAX_CACHE_DIR"):
        return Path(os.environ["POBAX_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pobax"


def texture_cache_file(block_pixels: int = BLOCK_PIXELS) -> Path:
    version = importlib.metadata.version("craftax")
    return cache_dir() / f"craftax-{version}-textures-{block_pixels}px.npz"


_LOCK = threading.Lock()


def _save_textures(path: Path, textures: dict) -> None:
    arrays = {}
    for name, value in textures.items():
        if isinstance(value, list):  # e.g. player_textures: a list of arrays of one shape
            arrays[f"list:{name}"] = np.stack([np.asarray(v) for v in value])
        else:
            arrays[name] = np.asarray(value)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def _load_texture_file(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as f:
        out = {}
        for key in f.files:
            if key.startswith("list:"):
                out[key[len("list:"):]] = [jnp.asarray(a) for a in f[key]]
            else:
                out[key] = jnp.asarray(f[key])
    return out


@functools.lru_cache(maxsize=None)
def textures(block_pixels: int = BLOCK_PIXELS) -> dict:
    """Craftax's texture dictionary for `block_pixels`-pixel blocks (cached in `cache_dir()`)."""
    from craftax.craftax.constants import load_all_textures_given_size

    path = texture_cache_file(block_pixels)
    with jax.ensure_compile_time_eval():  # concrete arrays even if first called while tracing
        if path.exists():
            try:
                return _load_texture_file(path)
            except Exception:  # a corrupt or partial cache: rebuild it
                pass
        with jax.numpy_rank_promotion("allow"):
            built = load_all_textures_given_size(block_pixels)
        try:
            _save_textures(path, built)
        except OSError:  # unwritable cache directory: work without a cache
            pass
        return _load_texture_file(path) if path.exists() else built


@functools.lru_cache(maxsize=None)
def pixel_renderer(block_pixels: int = BLOCK_PIXELS):
    """Craftax's pixel renderer (map and inventory) at `block_pixels` pixels per block."""
    from craftax.craftax import renderer

    tex = textures(block_pixels)
    with _LOCK:
        original = renderer.load_all_textures
        renderer.load_all_textures = lambda: {block_pixels: tex}
        try:
            with jax.ensure_compile_time_eval():
                return renderer.make_craftax_pixel_renderer(block_pixels)
        finally:
            renderer.load_all_textures = original


class _Craftax:
    """The Craftax functions used here, imported once (outside any trace)."""

    def __init__(self):
        with jax.ensure_compile_time_eval(), jax.numpy_rank_promotion("allow"):
            from craftax.craftax.craftax_state import EnvParams, StaticEnvParams
            from craftax.craftax.game_logic import craftax_step
            from craftax.craftax.renderer import render_craftax_symbolic
            from craftax.craftax.util.game_logic_utils import has_beaten_boss
            from craftax.craftax.world_gen.world_gen import generate_world
        self.EnvParams = EnvParams
        self.static_params = StaticEnvParams()
        self.craftax_step = craftax_step
        self.render_symbolic = render_craftax_symbolic
        self.has_beaten_boss = has_beaten_boss
        self.generate_world = generate_world


@functools.lru_cache(maxsize=None)
def _craftax() -> _Craftax:
    return _Craftax()


class CraftaxNoInventory(AbstractEnvironment):
    """No-inventory Crafter: full Craftax with the inventory cropped out of the pixel observation.

    The state is Craftax's `EnvState`. `terminated`: the player died or beat the final boss; `truncated`:
    Craftax's own time limit (`max_timesteps`, Craftax's default 100000) was reached without terminating.
    `info["achievements"]`: float32 `(67,)`, 1.0 for each achievement unlocked in the episode so far (on the
    step that ends an episode: that episode's achievements).
    """

    observabilities: ClassVar[tuple[str, ...]] = ("partial", "full")
    observability: str = eqx.field(static=True, default="partial")
    max_timesteps: int = eqx.field(static=True, default=DEFAULT_MAX_TIMESTEPS)

    def __check_init__(self):
        if self.observability not in self.observabilities:
            raise ValueError(
                f"Unknown observability {self.observability!r}; expected one of {self.observabilities}."
            )
        if self.max_timesteps < 1:
            raise ValueError(f"max_timesteps must be >= 1, got {self.max_timesteps}.")
        # Import Craftax and build the textures now, outside any trace.
        _craftax()
        if self.observability == "partial":
            pixel_renderer(BLOCK_PIXELS)

    @property
    def observation_space(self) -> Box:
        if self.observability == "partial":
            return Box(0.0, 255.0, PIXEL_SHAPE, jnp.uint8)
        return Box(0.0, float("inf"), (SYMBOLIC_SIZE,), jnp.float32)

    @property
    def action_space(self) -> Discrete:
        return Discrete(NUM_ACTIONS)

    @property
    def gamma(self) -> float:
        return 0.99

    @property
    def max_steps_in_episode(self) -> int:
        return self.max_timesteps

    def _params(self):
        return _craftax().EnvParams(max_timesteps=self.max_timesteps)

    def render_full_pixels(self, state) -> Array:
        """Craftax's render at 3 px per block, map and inventory: float `(39, 33, 3)` (for tests/figures)."""
        with jax.numpy_rank_promotion("allow"):
            return pixel_renderer(BLOCK_PIXELS)(state)

    def _obs(self, state) -> Array:
        if self.observability == "partial":
            pixels = self.render_full_pixels(state)[: PIXEL_SHAPE[0]]  # keep the map rows only
            return jnp.clip(jnp.round(pixels), 0, 255).astype(jnp.uint8)
        with jax.numpy_rank_promotion("allow"):
            return _craftax().render_symbolic(state).astype(jnp.float32)

    @staticmethod
    def _info(state) -> dict[str, Array]:
        return {"achievements": state.achievements.astype(jnp.float32)}

    def reset(self, *, key: PRNGKeyArray) -> tuple[Any, TimeStep]:
        c = _craftax()
        with jax.numpy_rank_promotion("allow"):
            state = c.generate_world(key, self._params(), c.static_params)
        return state, timestep(self._obs(state), info=self._info(state))

    def step(self, state, action: Array, *, key: PRNGKeyArray) -> tuple[Any, TimeStep]:
        c = _craftax()
        with jax.numpy_rank_promotion("allow"):
            state, reward = c.craftax_step(key, state, jnp.asarray(action, jnp.int32), self._params(),
                                           c.static_params)
            terminated = jnp.logical_or(state.player_health <= 0, c.has_beaten_boss(state, c.static_params))
        truncated = jnp.logical_and(state.timestep >= self.max_timesteps, ~terminated)
        return state, timestep(self._obs(state), reward, terminated, truncated, info=self._info(state))


# --------------------------------------------------------------------------------------------------------------
# Auto-reset from fresh worlds generated only for the environments that are done.


def _reset_done(env: AbstractEnvironment, pool_size: int, done, key, state, obs):
    """`(state, obs)` with done environments replaced by `env.reset(key=key)`, generating only what is needed.

    Per environment (unbatched) this is `lax.cond(done, reset, keep)`. Under `vmap` over N environments a
    custom batching rule replaces the default (which would turn the cond into a select and reset all N): the
    done environments are ranked; a `while_loop` takes them P = `pool_size` at a time, generates P worlds
    (vmapped) from the done environments' own keys and scatters them into their rows. A step on which no
    environment is done generates nothing; k done environments cost ceil(k / P) rounds of P worlds.
    """
    dyn, static = eqx.partition(env, eqx.is_array)

    def reset_one(dyn_env, k):
        s0, ts0 = eqx.combine(dyn_env, static).reset(key=k)
        return s0, ts0.obs

    @jax.custom_batching.custom_vmap
    def reset_where(dyn_env, d, k, s, o):
        return jax.lax.cond(d, lambda: reset_one(dyn_env, k), lambda: (s, o))

    @reset_where.def_vmap
    def _rule(axis_size, in_batched, dyn_env, d, k, s, o):
        dyn_b, d_b, k_b, s_b, o_b = in_batched

        def batch(x, b):
            return x if b else jnp.broadcast_to(x, (axis_size, *x.shape))

        d = batch(d, d_b)
        k = batch(k, k_b)
        s = jax.tree.map(batch, s, s_b)
        o = jax.tree.map(batch, o, o_b)
        out_batched = jax.tree.map(lambda _: True, (s, o))
        if any(jax.tree.leaves(dyn_b)):  # the environment itself is batched: reset every row, then select
            s0, o0 = jax.vmap(reset_one)(dyn_env, k)
            sel = lambda a, b: jnp.where(jnp.reshape(d, (-1,) + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
            return jax.tree.map(sel, (s0, o0), (s, o)), out_batched

        n = axis_size
        p = min(pool_size, n)
        d = d.astype(bool)
        rank = jnp.cumsum(d.astype(jnp.int32)) - 1  # rank of each done environment among the done ones
        n_done = jnp.sum(d.astype(jnp.int32))

        def cond(carry):
            return carry[0] < n_done

        def body(carry):
            served, s, o = carry
            # The next P done environments (ranks served .. served + P - 1); missing ones are index n.
            (idx,) = jnp.nonzero(d & (rank >= served), size=p, fill_value=n)
            s0, o0 = jax.vmap(reset_one, in_axes=(None, 0))(dyn_env, k[jnp.minimum(idx, n - 1)])
            put = lambda a, b: a.at[idx].set(b, mode="drop")  # noqa: E731  (index n is dropped)
            return served + p, jax.tree.map(put, s, s0), jax.tree.map(put, o, o0)

        _, s, o = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), s, o))
        return (s, o), out_batched

    return reset_where(dyn, done, key, state, obs)


class PoolAutoReset(AbstractWrapper):
    """Auto-reset (same contract as `AutoReset`) that generates new worlds only for environments that are done.

    On the step that ends an episode, `obs` is the first observation of the next episode, `final_obs` the
    last observation of the ended one, and `reward`, `terminated`, `truncated` and `info` belong to the ended
    episode; the next `step` acts in the new episode.

    Reset distribution. Exactly as `AutoReset`: the step key is split into `(k_step, k_reset)` the same way and
    a done environment's new episode is `env.reset(key=k_reset)` with its own `k_reset`, so every episode
    starts from an independently generated world, bit-identical to `AutoReset` given the same keys (a test
    checks this). Only the cost differs: under `vmap` over N environments, the worlds are generated in rounds
    of P = `pool_size` (a `while_loop`), each round for the next P done environments in batch order, until all
    done environments have one. Any number of environments may finish on the same step (more than P only
    costs more rounds); none reuses another's world; no world is generated on a step where none finishes.
    Unbatched (one environment) the reset is a `lax.cond` on `done`.

    `pool_size`: worlds generated per round (<= N). Larger suits accelerators (a round of P worlds costs about
    as much as one), small suits CPUs (cost is linear in P).
    """

    env: AbstractEnvironment
    pool_size: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        if self.pool_size < 1:
            raise ValueError(f"pool_size must be >= 1, got {self.pool_size}.")

    def reset(self, *, key: PRNGKeyArray):
        s, ts = self.env.reset(key=key)
        return s, eqx.tree_at(lambda x: x.final_obs, ts, ts.obs, is_leaf=lambda x: x is None)

    def step(self, state, action: Array, *, key: PRNGKeyArray):
        k_step, k_reset = jax.random.split(key)
        s, ts = self.env.step(state, action, key=k_step)
        s_next, obs = _reset_done(self.env, self.pool_size, ts.done, k_reset, s, ts.obs)
        return s_next, TimeStep(
            obs=obs,
            reward=ts.reward,
            terminated=ts.terminated,
            truncated=ts.truncated,
            final_obs=ts.obs,
            info=ts.info,
        )


def pool_auto_reset(pool_size: int = 8):
    """An `EnvFamily.auto_reset` factory: `env -> PoolAutoReset(env, pool_size)`."""
    return functools.partial(PoolAutoReset, pool_size=pool_size)


def _build(observability: str, **kw) -> CraftaxNoInventory:
    try:
        import craftax  # noqa: F401
    except ImportError as e:
        raise ImportError(
            "craftax_pixels needs Craftax: pip install 'pobax-bench[craftax]' (or pip install craftax)."
        ) from e
    return CraftaxNoInventory(observability=observability, **kw)


def craftax_families() -> list[EnvFamily]:
    """The `craftax_pixels` family (paper appendix "No-inventory Crafter")."""
    return [
        EnvFamily(
            template="craftax_pixels",
            pattern=r"craftax_pixels",
            build=_build,
            observabilities=CraftaxNoInventory.observabilities,
            # Paper §"No-inventory Crafter": visual occlusion (the inventory is cropped, the view is local),
            # spatial uncertainty (a procedurally generated world seen through a 9 x 11 window) and object
            # uncertainty & tracking (mobs leave the view; items and stats must be remembered).
            categories=("visual occlusion", "spatial uncertainty", "object uncertainty & tracking"),
            # Craftax truncates itself at `max_timesteps`; the registry's TimeLimit is the same bound.
            max_steps=DEFAULT_MAX_TIMESTEPS,
            registered=("craftax_pixels",),
            # Paper appendix: 256 envs, hidden size 512, 5e8 steps, TrXL embed 220.
            recommended=dict(
                hidden_size=512, num_envs=256, total_steps=500_000_000, embed_size=220, entropy_coeff=0.01
            ),
            # Paper table "No-inventory Crafter Best Hyperparameters".
            best={
                "full": dict(lr=2.5e-4, lambda0=0.7),
                "memoryless": dict(lr=2.5e-5, lambda0=0.95),
                "gru": dict(lr=2.5e-4, lambda0=0.5, action_concat=True),
                "trxl": dict(lr=2.5e-5, lambda0=0.7, action_concat=True),
                "ld": dict(lr=2.5e-4, lambda0=0.1, lambda1=0.95, ld_weight=0.25, action_concat=True),
            },
            extra="craftax",
            auto_reset=pool_auto_reset(),
        )
    ]


__all__ = [
    "ACHIEVEMENT_NAMES",
    "CraftaxNoInventory",
    "PoolAutoReset",
    "cache_dir",
    "craftax_families",
    "pool_auto_reset",
]
