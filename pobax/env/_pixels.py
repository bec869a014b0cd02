"""Visual continuous control: Brax robots seen through single 32x32 RGB frames (paper: `ant_pixels`,
`halfcheetah_pixels`; appendix "Visual Continuous Control"), plus `hopper_pixels` and `walker2d_pixels`.

The dynamics, reward, termination and reset noise are those of the masked MuJoCo environments (`_brax.py`:
Brax's robot, MJX physics pinned by `PHYSICS_BY_ROBOT`). Observabilities:

- `partial`: one RGB frame, uint8 `(image_size, image_size, 3)` (32 by default, as the paper), no frame
  stacking, so velocities are not observable and parts of the robot can hide others.
- `full`: Brax's full state observation (what `BraxEnv` gives for the `-F-` mask; 27 numbers for Ant, 17 for
  HalfCheetah, 11 for Hopper, 17 for Walker).

The paper rendered with the Madrona MJX renderer (CUDA only, one batch of environments, not vmappable). Here
frames come from a pure-JAX ray caster (`_raycast.py`) over the MJX geoms, so environments jit and vmap over
environments, seeds and hyperparameters on CPU and GPU. The frames therefore do not look like the paper's:
the camera follows the torso horizontally with a fixed orientation and a fixed height (the robot's height and
pitch are visible against the frame), geoms keep the model's colour with Lambert shading under a directional
light, and the floor is a checkerboard so that forward motion shows. Camera per robot (`CAMERAS`): a side view
for HalfCheetah, Hopper and Walker (looking along +y, +x to the right), an elevated three-quarter view from
behind-left for Ant. The thinnest limbs (HalfCheetah's 9.2 cm thick capsules) are about 1.4 px wide at 32 px.

Frames are rendered from the geom poses of the MJX data after the step. Like Brax's own `x` (and the torso
height in the state observation), MJX computes those poses before integrating the last physics substep, so a
frame lags the joint positions by one physics substep (a fraction of the control step).

`physics="positional"` (`--env-options physics=positional`) runs Brax's positional pipeline instead, the physics the
original implementation's pixel environments run under their renderer (`docs/parity.md`). Brax's pipelines other than
MJX (positional, generalized, spring) carry no geom poses, so frames are drawn from their link frames (`geom_poses`:
each geom's pose is its body's link frame composed with the geom's offset).
"""

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._base import AbstractEnvironment, TimeStep, check_seed, random_rollout
from ._brax import PHYSICS, PHYSICS_BY_ROBOT, BraxEnv, BraxState, load_brax_env
from ._raycast import Camera, Scene, render
from ._mujoco_families import ACTION_CONCAT
from ._registry import EnvFamily, discrepancy_terms
from ._spaces import Box

# Environment ID prefix -> robot name in `_brax.ROBOTS`.
PIXEL_ROBOTS: dict[str, str] = {
    "ant": "Ant",
    "halfcheetah": "HalfCheetah",
    "hopper": "Hopper",
    "walker2d": "Walker",
}

# Camera per robot. Side views look along +y from y = -distance at a fixed height; Ant's view is from behind
# and to the left of the direction of travel (+x), 35 degrees down. `fovy` and `distance` are chosen so the
# whole robot fits with a margin for its motion, with limbs at least a pixel wide at 32 px.
CAMERAS: dict[str, Camera] = {
    "HalfCheetah": Camera(distance=2.6, azimuth=90.0, elevation=-10.0, fovy=45.0, offset=(0.0, 0.0, 0.4)),
    "Hopper": Camera(distance=3.0, azimuth=90.0, elevation=-5.0, fovy=45.0, offset=(0.0, 0.0, 0.8)),
    "Walker": Camera(distance=3.0, azimuth=90.0, elevation=-5.0, fovy=45.0, offset=(0.0, 0.0, 0.8)),
    "Ant": Camera(distance=3.6, azimuth=45.0, elevation=-35.0, fovy=45.0, offset=(0.0, 0.0, 0.3)),
}

TORSO_BODY = 1  # body 0 is the world; body 1 is every robot's torso


@functools.lru_cache(maxsize=None)
def load_scene(robot: str, physics: str, image_size: int, supersample: int = 1, shadows: bool = True) -> Scene:
    """The ray caster's scene for a robot (cached: environments made twice are equal)."""
    return Scene.from_model(
        load_brax_env(robot, physics).sys,
        CAMERAS[robot],
        image_size,
        image_size,
        supersample=supersample,
        shadows=shadows,
    )


#: The largest side, in rendered pixels (image_size × supersample), of a frame: 16 times the paper's 32.
MAX_IMAGE_SIZE = 512


class PixelBrax(AbstractEnvironment[BraxState]):
    """A Brax robot observed through a rendered RGB frame (`partial`) or its full state vector (`full`)."""

    robot: str = eqx.field(static=True)
    observability: str = eqx.field(static=True)
    physics: str = eqx.field(static=True)
    image_size: int = eqx.field(static=True)
    brax: BraxEnv
    scene: Scene = eqx.field(static=True)

    observabilities = ("partial", "full")

    def __init__(
        self,
        robot: str,
        observability: str = "partial",
        physics: str | None = None,
        image_size: int = 32,
        supersample: int = 1,
        shadows: bool = True,
    ):
        if robot not in CAMERAS:
            raise ValueError(f"Unknown robot {robot!r}; expected one of {', '.join(CAMERAS)}.")
        if observability not in self.observabilities:
            raise ValueError(f"Pixel MuJoCo has observabilities {self.observabilities}, got {observability!r}.")
        for name, value, most in (("image_size", image_size, MAX_IMAGE_SIZE), ("supersample", supersample, 16)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= most:
                raise ValueError(f"Pixel MuJoCo's {name} must be an integer in [1, {most}], got {value!r}.")
        if image_size * supersample > MAX_IMAGE_SIZE:  # the rays cast per frame, and their buffers, grow as its square
            raise ValueError(f"Pixel MuJoCo renders image_size × supersample = {image_size * supersample} pixels a "
                             f"side, more than {MAX_IMAGE_SIZE}; lower either.")
        physics = PHYSICS_BY_ROBOT[robot] if physics is None else physics
        self.brax = BraxEnv(robot, "F", "full", physics)  # refuses an unknown physics setting
        self.robot = robot
        self.observability = observability
        self.physics = physics
        self.image_size = image_size
        self.scene = load_scene(robot, physics, image_size, supersample, shadows)

    @property
    def gamma(self) -> float:
        return self.brax.gamma

    @property
    def observation_space(self) -> Box:
        if self.observability == "partial":
            return Box(0.0, 255.0, (self.image_size, self.image_size, 3), jnp.uint8)
        return self.brax.observation_space

    @property
    def action_space(self) -> Box:
        return self.brax.action_space

    @property
    def observation_names(self) -> tuple[str, ...] | None:
        """What each entry of the `full` observation is (`None` for images)."""
        return self.brax.observation_names if self.observability == "full" else None

    def render(self, state: BraxState) -> Array:
        """The RGB frame of a state, uint8 `(image_size, image_size, 3)` (whatever the observability)."""
        data = state.inner.pipeline_state
        if PHYSICS[self.physics].backend == "mjx":
            return render(self.scene, data.geom_xpos, data.geom_xmat, data.xpos[TORSO_BODY])
        xpos, xmat = geom_poses(self.brax.brax_env.sys, data.x.pos, data.x.rot)  # Brax's other pipelines: link frames
        return render(self.scene, xpos, xmat, data.x.pos[TORSO_BODY - 1])

    def observe(self, state: BraxState) -> Array:
        if self.observability == "partial":
            return self.render(state)
        return self.brax.observe(state)

    def _with_obs(self, state: BraxState, ts: TimeStep) -> TimeStep:
        if self.observability == "full":
            return ts
        return eqx.tree_at(lambda t: t.obs, ts, self.render(state))

    def reset(self, *, key: PRNGKeyArray) -> tuple[BraxState, TimeStep]:
        state, ts = self.brax.reset(key=key)
        return state, self._with_obs(state, ts)

    def step(
        self, state: BraxState, action: Float[Array, " action"], *, key: PRNGKeyArray
    ) -> tuple[BraxState, TimeStep]:
        state, ts = self.brax.step(state, action, key=key)
        return state, self._with_obs(state, ts)


def geom_poses(
    sys: Any, link_pos: Float[Array, "links 3"], link_rot: Float[Array, "links 4"]
) -> tuple[Float[Array, "geoms 3"], Float[Array, "geoms 3 3"]]:
    """World positions and rotation matrices of every geom (MJX's `geom_xpos`, `geom_xmat`) from the link frames of
    Brax's maximal-coordinate pipelines (`pipeline_state.x`: link `i` is MuJoCo body `i + 1`; body 0, the world,
    is fixed): each geom's pose is its body's frame composed with the geom's offset (`geom_pos`, `geom_quat`)."""
    from brax import math as bmath

    body = np.asarray(sys.geom_bodyid)
    pos = jnp.concatenate([jnp.zeros((1, 3), link_pos.dtype), link_pos])[body]
    rot = jnp.concatenate([jnp.array([[1.0, 0.0, 0.0, 0.0]], link_rot.dtype), link_rot])[body]
    gpos = jnp.asarray(sys.geom_pos, link_pos.dtype)
    gquat = jnp.asarray(sys.geom_quat, link_rot.dtype)
    xpos = pos + jax.vmap(bmath.rotate)(gpos, rot)
    xmat = jax.vmap(bmath.quat_to_3x3)(jax.vmap(bmath.quat_mul)(rot, gquat))
    return xpos, xmat


# --- Rendering helpers -----------------------------------------------------------------------------------------


def render_frames(env, num_steps: int, seed: int = 0, **overrides: Any) -> np.ndarray:
    """`num_steps` observations of `env` under uniformly random actions, stacked: the first after reset, then one per
    step; for a pixel environment, frames `(T, H, W, 3)` uint8.

    `env`: a registered environment's name, made by `make` with its `partial` observation (so with the registry's
    time limit and auto-reset; `overrides` go to its constructor, e.g. `image_size=64`, `supersample=2` for nicer
    pictures), or an environment already made (by `make`, wrapped, or of your own), rolled out as it is.
    """
    from ._registry import make

    if isinstance(env, str):
        env = make(env, "partial", **overrides)
    elif overrides:
        raise TypeError(f"render_frames: constructor overrides ({', '.join(overrides)}) apply to an environment's "
                        f"name; make the environment with them instead.")
    check_seed(seed)
    run = jax.jit(lambda key: random_rollout(env, num_steps, key, lambda state, obs: obs)[0])
    return np.asarray(run(jax.random.key(seed)))


def save_frame_grid(frames: np.ndarray, path: str, cols: int = 8, scale: int = 4, gap: int = 1) -> None:
    """Write frames `(T, H, W, 3)` (uint8, or floats in [0, 1]) as one PNG grid, `cols` frames a row, each
    pixel drawn `scale` times larger (nearest neighbour), frames separated by `gap` white pixels."""
    import matplotlib.image

    frames = np.asarray(frames)
    if frames.dtype != np.uint8:
        frames = np.clip(np.round(frames * 255.0), 0, 255).astype(np.uint8)
    frames = frames.repeat(scale, axis=1).repeat(scale, axis=2)
    t, h, w, c = frames.shape
    cols = max(1, min(cols, t))
    rows = -(-t // cols)
    grid = np.full((rows * (h + gap) - gap, cols * (w + gap) - gap, c), 255, np.uint8)
    for i, frame in enumerate(frames):
        r, q = divmod(i, cols)
        grid[r * (h + gap) : r * (h + gap) + h, q * (w + gap) : q * (w + gap) + w] = frame
    matplotlib.image.imsave(path, grid)


# --- Registration ------------------------------------------------------------------------------------------


#: The ceiling (`full`) sees Brax's state, whose entries range over orders of magnitude, and earns rewards of
#: hundreds per episode: it trains with the running normalisation of both that masked MuJoCo's agents use. Not in the
#: paper. ant_pixels, 3 seeds × 16 envs, undiscounted return after 1.76M steps: 147 normalised vs 47 raw (H100,
#: 7 of 20 chunks, benchmarks/results/ant-pixels-ceiling-norm-h100.json); on the CPU, 1 seed × 2M steps, 89 vs 24
#: (ant-pixels-ceiling-norm-cpu.json). The pixel agents keep their frames (scaled by the CNN) and raw rewards.
_CEILING_NORMALISATION = dict(normalize_obs=True, normalize_reward=True)


def _family(prefix: str, best: dict, figure: dict | None = None, ceiling_memory: str = "memoryless",
            paper_full: dict | None = None) -> EnvFamily:
    name = f"{prefix}_pixels"
    robot = PIXEL_ROBOTS[prefix]
    best = {**best, "full": {**best.get("full", {}), **_CEILING_NORMALISATION}}
    paper_full = {**(paper_full or {}), "normalize_obs": False, "normalize_reward": False}
    return EnvFamily(
        template=name,
        pattern=name,
        build=lambda observability, **kw: PixelBrax(robot, observability, **kw),
        observabilities=PixelBrax.observabilities,
        # Paper §5 "Visual Mujoco": single frames hide velocities (moment features) and parts of the robot
        # can occlude others (visual occlusion).
        categories=("visual occlusion", "moment features"),
        # Episodes end by truncation after 1000 steps (bootstrapped), or by Brax's termination.
        max_steps=1000,
        registered=(name,) if prefix in ("ant", "halfcheetah") else (),
        # Paper appendix "Visual Continuous Control": hidden size 512, 5e6 steps, transformer embed size 220;
        # the rest are the general defaults (4 environments, entropy 0.01).
        recommended=dict(hidden_size=512, num_envs=4, total_steps=5_000_000, entropy_coeff=0.01, embed_size=220),
        best=best,
        extra="mujoco",
        # `reduced` runs 16 environments per seed, not the paper's 4: on an H200 (3 seeds in one program, ant_pixels)
        # the floor runs 4.4k env steps/s at 4, 15.8k at 16 and 18.4k at 64 (the GRU 4.0k and 13.3k): at 4 an agent
        # needs about an hour, at 16 a quarter (benchmarks/results/pixels-envs-h200.json). Whether 4 learns better
        # at 5M steps (4× the updates) is not measured. `--budget paper` keeps 4.
        budgets={"reduced": dict(total_steps=5_000_000, num_seeds=3, num_envs=16)},
        paper_figure=figure or {},  # undiscounted, read off the paper's results figure
        paper_metric="return",
        paper_original={"full": paper_full},
        ceiling_memory=ceiling_memory,
        # One program sharded over 2 GPUs dies in XLA's GPU compiler (a segmentation fault in backend_compile;
        # ant_pixels GRU × 5 seeds × 16 envs, JAX 0.11.2, four H200s: `benchmarks/bench_train.py --devices 2
        # --cases ant_pixels:gru:5`); on one GPU it runs at 6.0k env steps/s. Several GPUs: `benchmark --jobs`.
        single_device=True,
    )


def pixel_mujoco_families() -> list[EnvFamily]:
    """`ant_pixels` and `halfcheetah_pixels` (the paper's, with its best hyperparameters: tables "Ant Best
    Hyperparameters" and "Halfcheetah Best Hyperparameters"; every ceiling normalised, halfcheetah_pixels's a GRU),
    `hopper_pixels` and `walker2d_pixels` (none, but for the λ-discrepancy agent's λ1 and β)."""
    ant_best = {
        "full": dict(lr=2.5e-4, lambda0=0.5),
        "memoryless": dict(lr=2.5e-4, lambda0=0.1),
        "gru": dict(lr=2.5e-4, lambda0=0.7, **ACTION_CONCAT),
        "trxl": dict(lr=2.5e-4, lambda0=0.5, **ACTION_CONCAT),
        "ld": dict(lr=2.5e-4, lambda0=0.1, lambda1=0.5, ld_weight=0.5, **ACTION_CONCAT),
    }
    # Not the paper's: its halfcheetah_pixels ceiling (an MLP on the state, λ0 0.5) trails the GRU on frames (5M × 3
    # on an H100: 1461 after 4M steps against the GRU's 2220). As for HalfCheetah-V, the ceiling is a GRU on the state
    # with the previous action and λ0 0.9; CPU, 1 seed × 2M steps, undiscounted return at the end
    # (benchmarks/results/halfcheetah-pixels-ceiling-cpu.json): GRU 3316, MLP at λ0 0.9 with the previous action
    # 1807, MLP at the paper's λ0 0.5 897 (raw state and rewards: 982). Shipped (5M × 3, H100): 3610 [3340, 3830].
    cheetah_best = {
        "full": dict(lr=2.5e-4, lambda0=0.9, **ACTION_CONCAT),
        "memoryless": dict(lr=2.5e-4, lambda0=0.7),
        "gru": dict(lr=2.5e-4, lambda0=0.7, **ACTION_CONCAT),
        "trxl": dict(lr=2.5e-4, lambda0=0.7, **ACTION_CONCAT),
        "ld": dict(lr=2.5e-4, lambda0=0.95, lambda1=0.95, ld_weight=0.5, **ACTION_CONCAT),
    }
    return [
        _family("ant", ant_best, dict(ceiling=1200.0, gru=700.0, ld=600.0, trxl=650.0, floor=350.0)),
        _family("halfcheetah", cheetah_best, dict(ceiling=2500.0, gru=1300.0, ld=1000.0, trxl=1000.0, floor=900.0),
                ceiling_memory="gru", paper_full=dict(lambda0=0.5, action_concat=False)),
        # No paper table: the defaults, and for the λ-discrepancy agent halfcheetah's λ1 and β (without which it
        # would have no discrepancy loss: the defaults' β = 0).
        _family("hopper", discrepancy_terms(cheetah_best)),
        _family("walker2d", discrepancy_terms(cheetah_best)),
    ]
