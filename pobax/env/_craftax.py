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
ended. The family's auto-reset is `AutoReset(env, pool_size=8)`, which generates worlds only for the environments
that are done, 8 at a time; see `AutoReset`.
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

from .._paths import cache_dir
from ._base import AbstractEnvironment, TimeStep, timestep
from ._registry import EnvFamily
from ._spaces import Box, Discrete
from ._wrappers import AutoReset

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
    step that ends an episode: that episode's achievements). Training logs their per-episode success rates as
    columns `achievement_<name>` (`episode_metrics`).
    """

    observabilities: ClassVar[tuple[str, ...]] = ("partial", "full")
    observability: str = eqx.field(static=True, default="partial")
    max_timesteps: int = eqx.field(static=True, default=DEFAULT_MAX_TIMESTEPS)

    def __check_init__(self):
        if self.observability not in self.observabilities:
            raise ValueError(
                f"Unknown observability {self.observability!r}; expected one of {self.observabilities}."
            )
        m = self.max_timesteps
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= 2**31 - 1:
            # Craftax counts an episode's steps in int32: a larger bound overflowed deep in the first jitted step.
            raise ValueError(f"Craftax's max_timesteps must be an integer in [1, 2**31 - 1] (steps, counted in int32), "
                             f"got {m!r}.")
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

    @property
    def episode_metrics(self) -> dict[str, tuple[str, ...]]:
        return {"achievements": tuple(f"achievement_{name}" for name in ACHIEVEMENT_NAMES)}

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
            action = self.action_space.as_action(action)
            action = jnp.where((action >= 0) & (action < NUM_ACTIONS), action, 0)  # outside the space: Craftax's NOOP
            state, reward = c.craftax_step(key, state, action, self._params(), c.static_params)
            terminated = jnp.logical_or(state.player_health <= 0, c.has_beaten_boss(state, c.static_params))
        truncated = jnp.logical_and(state.timestep >= self.max_timesteps, ~terminated)
        return state, timestep(self._obs(state), reward, terminated, truncated, info=self._info(state))


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
            budgets={"reduced": dict(total_steps=25_000_000, num_seeds=3)},
            # Undiscounted, read off the paper's results figure.
            paper_figure=dict(ceiling=21.5, gru=16.5, ld=17.5, trxl=15.5, floor=10.0),
            paper_metric="return",
            # reset only the environments that are done, 8 worlds per round (`AutoReset.pool_size`)
            auto_reset=functools.partial(AutoReset, pool_size=8),
        )
    ]


__all__ = [
    "ACHIEVEMENT_NAMES",
    "CraftaxNoInventory",
    "cache_dir",
    "craftax_families",
]
