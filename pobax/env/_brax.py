"""Masked continuous control: Brax robots (MuJoCo physics through MJX) with position- or velocity-only views.

IDs `{Walker,Ant,Hopper,HalfCheetah}-{F,P,V}-v0` (paper: `Walker-V-v0`, `HalfCheetah-V-v0`; appendix "Masked
Continuous Control"). The robot is Brax's `walker2d`, `ant`, `hopper` or `halfcheetah` with Brax's reward,
termination and reset noise; the letter picks what the agent sees of Brax's observation
`concat(positions, velocities)`:

- `F`: everything (Brax's default observation).
- `P`: the position part only (`qpos` without the global x (and y) coordinates).
- `V`: the velocity part only (`qvel`).

Observabilities: every ID has `partial` (its mask) and `full` (the `F` observation), so `make("Walker-V-v0",
"full")` is the fully observable ceiling of `Walker-V-v0` with identical dynamics. For `-F-` IDs `partial` is
the same observation as `full`.

Kept indices of Brax's observation `obs` and where each entry is in the MJX state (`ps` = the Brax state's
`pipeline_state`: `ps.q` is MuJoCo's `qpos`, `ps.qd` its `qvel`, `ps.x.pos` the bodies' `xpos`). `P` keeps the
position rows, `V` the velocity rows; every P entry is a position and every V entry a velocity (the joints'
positions and velocities are never mixed). `env.observation_names` names each entry.

Walker (Brax `walker2d`; 17 = 8 P + 9 V; 6 actions):

| obs   | part | meaning                                           | MJX state                    |
|-------|------|---------------------------------------------------|------------------------------|
| 0     | P    | torso height                                      | `ps.x.pos[0, 2]` (*)         |
| 1     | P    | torso pitch (rooty)                               | `ps.q[2]`                    |
| 2-4   | P    | right thigh, leg, foot angles                     | `ps.q[3:6]`                  |
| 5-7   | P    | left thigh, leg, foot angles                      | `ps.q[6:9]`                  |
| 8-10  | V    | torso x velocity, z velocity, pitch rate          | `clip(ps.qd[0:3], -10, 10)`  |
| 11-16 | V    | right thigh, leg, foot, left thigh, leg, foot rates | `clip(ps.qd[3:9], -10, 10)` |

Hopper (Brax `hopper`; 11 = 5 P + 6 V; 3 actions):

| obs   | part | meaning                                   | MJX state                    |
|-------|------|-------------------------------------------|------------------------------|
| 0     | P    | torso height                              | `ps.x.pos[0, 2]` (*)         |
| 1     | P    | torso pitch (rooty)                       | `ps.q[2]`                    |
| 2-4   | P    | thigh, leg, foot angles                   | `ps.q[3:6]`                  |
| 5-7   | V    | torso x velocity, z velocity, pitch rate  | `clip(ps.qd[0:3], -10, 10)`  |
| 8-10  | V    | thigh, leg, foot rates                    | `clip(ps.qd[3:6], -10, 10)`  |

HalfCheetah (Brax `halfcheetah`; 17 = 8 P + 9 V; 6 actions; velocities are not clipped):

| obs   | part | meaning                                            | MJX state      |
|-------|------|----------------------------------------------------|----------------|
| 0     | P    | torso z (rootz slide)                              | `ps.q[1]`      |
| 1     | P    | torso pitch (rooty)                                | `ps.q[2]`      |
| 2-7   | P    | back thigh, shin, foot, front thigh, shin, foot    | `ps.q[3:9]`    |
| 8-10  | V    | torso x velocity, z velocity, pitch rate           | `ps.qd[0:3]`   |
| 11-16 | V    | rates of the six joints, same order                | `ps.qd[3:9]`   |

Ant (Brax `ant`; 27 = 13 P + 14 V; 8 actions; no contact forces: Brax's default and only option):

| obs   | part | meaning                                              | MJX state       |
|-------|------|------------------------------------------------------|-----------------|
| 0     | P    | torso z                                              | `ps.q[2]`       |
| 1-4   | P    | torso orientation quaternion (w, x, y, z)            | `ps.q[3:7]`     |
| 5-12  | P    | hip_1, ankle_1, ..., hip_4, ankle_4 angles           | `ps.q[7:15]`    |
| 13-15 | V    | torso linear velocity (x, y, z; world frame)         | `ps.qd[0:3]`    |
| 16-18 | V    | torso angular velocity (x, y, z; torso frame)        | `ps.qd[3:6]`    |
| 19-26 | V    | the eight hip/ankle rates, same order                | `ps.qd[6:14]`   |

(*) Brax reads the torso height of Walker and Hopper from the kinematics, `xpos`, not from `qpos`: it is
`1.25 + qpos[1]` as of the start of the last physics substep (MJX computes kinematics before it integrates).
The global x (and Ant's y) position is never observed, as in Brax.

Actions are `Box(-1, 1, (action_size,))` (Walker 6, Hopper 3, HalfCheetah 6, Ant 8) and are clipped to the
box inside `step`. Brax's `done` (Walker, Hopper and Ant falling; HalfCheetah never) sets `terminated`;
episodes are otherwise cut at 1000 steps by the registry's `TimeLimit` (`truncated`, so that the learner
bootstraps from the final observation). Brax's own episode and auto-reset wrappers are not used.

`mask_layout="original"` (`--env-options mask_layout=original`) shows what the original release's masks show where
they differ from these (HalfCheetah; `ORIGINAL_MASKS`, docs/parity.md): a different observation, so a different task.

Physics. The dynamics of an ID are pinned, never chosen silently: `PHYSICS_BY_ROBOT` names the physics
setting of each robot (a key of `PHYSICS`), recorded on the environment as `env.physics`. All robots use
Brax's `mjx` backend (MJX, JAX implementation) with the Newton solver at 1 iteration and 4 line-search
iterations, the settings Brax itself ships for Ant. As shipped, Brax runs Walker, Hopper and HalfCheetah under
MJX with 4 Newton and 50 line-search iterations, 10-16x slower on CPU for the same model. Measured with
`git show 82e5b1f:benchmarks/bench_brax_backends.py` (run in that tree as its docstring shows:
`JAX_PLATFORMS=cpu python benchmarks/bench_brax_backends.py [--fidelity] --robots ... --physics ...`; 2-core CPU,
1024 environments, random actions, steps/s; the fidelity column is the mean one-step |obs - obs_shipped| / std(obs)
against Brax's MJX as shipped):

| robot       | pinned                | steps/s | shipped MJX | positional | fidelity (pinned / other) |
|-------------|-----------------------|---------|-------------|------------|---------------------------|
| Walker      | `mjx-newton-1-4`      | 19.7k   | 1.7k        | 12.2k      | 0.034 / 0.056 with damping |
| Hopper      | `mjx-newton-1-4`      | 22.6k   | 2.4k        | -          | 0.005 / 0.006 with damping |
| HalfCheetah | `mjx-newton-1-4`      | 12.3k*  | 1.0k        | 2.7k       | 0.099 / 0.022 with damping |
| Ant         | `mjx-newton-1-4`      | 8.7k    | (the same)  | 4.6k       | 0 (Brax's own Ant settings) |

(*) measured with damping kept (`mjx-newton-1-4-damp`); HalfCheetah's `mjx-newton-1-4` is not measured on the CPU.

`mjx-newton-1-4` also turns MuJoCo's implicit Euler damping off, as Brax does for Ant, HalfCheetah included:
keeping it (`physics="mjx-newton-1-4-damp"`, one-step dynamics 4.5x closer to shipped Brax) sends 4.9% of HalfCheetah
environments non-finite (NaN) in a stability check (measured with `git show 82e5b1f:benchmarks/brax_stability_check.py`,
run in that tree with its defaults of 1024 environments × 3000 random-action steps, H200), none with `mjx-newton-1-4`
or shipped MJX; a NaN environment poisons training. On the H200 the four pinned robots stay finite in that check:
Walker 794k, HalfCheetah 610k, Ant 641k, Hopper 1.13M random steps/s at 1024 envs. Another setting can be asked for
explicitly (`make(..., physics="mjx")`); it is then part of the environment's identity. Pinned with brax 0.14.2,
mujoco 4.0.0 and mujoco-mjx 3.17.0 (the robot models and reward code are Brax's).
"""

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray, PyTree

from ._base import AbstractEnvironment, TimeStep, timestep
from ._spaces import Box

MASKS = ("F", "P", "V")


@dataclasses.dataclass(frozen=True)
class Robot:
    """A Brax robot and how its observation splits into positions and velocities."""

    brax_name: str
    num_pos: int  # obs[:num_pos] are positions, obs[num_pos:] velocities
    num_vel: int
    action_size: int
    pos_names: tuple[str, ...]
    vel_names: tuple[str, ...]

    def __post_init__(self):
        assert len(self.pos_names) == self.num_pos and len(self.vel_names) == self.num_vel

    @property
    def obs_size(self) -> int:
        return self.num_pos + self.num_vel


_PLANAR_JOINTS = ("thigh", "leg", "foot", "thigh_left", "leg_left", "foot_left")
_CHEETAH_JOINTS = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
_ANT_JOINTS = tuple(f"{j}_{i}" for i in range(1, 5) for j in ("hip", "ankle"))

ROBOTS: dict[str, Robot] = {
    "Walker": Robot(
        "walker2d", 8, 9, 6,
        ("torso_z", "torso_pitch") + _PLANAR_JOINTS,
        ("torso_vx", "torso_vz", "torso_vpitch") + tuple(f"{j}_vel" for j in _PLANAR_JOINTS),
    ),
    "Hopper": Robot(
        "hopper", 5, 6, 3,
        ("torso_z", "torso_pitch") + _PLANAR_JOINTS[:3],
        ("torso_vx", "torso_vz", "torso_vpitch") + tuple(f"{j}_vel" for j in _PLANAR_JOINTS[:3]),
    ),
    "HalfCheetah": Robot(
        "halfcheetah", 8, 9, 6,
        ("torso_z", "torso_pitch") + _CHEETAH_JOINTS,
        ("torso_vx", "torso_vz", "torso_vpitch") + tuple(f"{j}_vel" for j in _CHEETAH_JOINTS),
    ),
    "Ant": Robot(
        "ant", 13, 14, 8,
        ("torso_z", "torso_qw", "torso_qx", "torso_qy", "torso_qz") + _ANT_JOINTS,
        ("torso_vx", "torso_vy", "torso_vz", "torso_wx", "torso_wy", "torso_wz")
        + tuple(f"{j}_vel" for j in _ANT_JOINTS),
    ),
}


# The original release's masks (`mask_layout="original"`), indices of Brax's observation, for the robots whose masks
# were compared with it (docs/parity.md, "Differences found" 2): its HalfCheetah-P keeps the torso's z and pitch, the
# back thigh and shin, and the rates of those and of the torso's x; its HalfCheetah-V the back foot and front leg's
# three angles and their rates, so it sees joint angles and not the torso's velocity. Its Walker masks are pobax's.
ORIGINAL_MASKS: dict[str, dict[str, tuple[int, ...]]] = {
    "HalfCheetah": {"P": (0, 1, 2, 3, 8, 9, 10, 11, 12), "V": (4, 5, 6, 7, 13, 14, 15, 16)},
    "Walker": {"P": tuple(range(8)), "V": tuple(range(8, 17))},
}
MASK_LAYOUTS = ("pobax", "original")


@dataclasses.dataclass(frozen=True)
class Physics:
    """A physics setting: a Brax backend and, for MJX, the constraint solver settings.

    `None` solver fields keep what Brax ships for the robot.
    """

    backend: str
    newton_iterations: int | None = None
    ls_iterations: int | None = None
    euler_damping: bool | None = None


PHYSICS: dict[str, Physics] = {
    # Brax's MJX environments exactly as shipped (Ant already has the Newton 1/4 settings).
    "mjx": Physics("mjx"),
    # The settings Brax ships for Ant's MJX backend, applied to every robot.
    "mjx-newton-1-4": Physics("mjx", newton_iterations=1, ls_iterations=4, euler_damping=False),
    # As above, keeping MuJoCo's implicit Euler damping of joint damping (more stable for stiff damping).
    "mjx-newton-1-4-damp": Physics("mjx", newton_iterations=1, ls_iterations=4, euler_damping=True),
    # Brax's own pipelines as shipped (positional and spring also change time step and gears of some robots).
    "positional": Physics("positional"),
    "generalized": Physics("generalized"),
    "spring": Physics("spring"),
}

# The pinned physics of each ID: speed and fidelity in the module docstring, measured with
# `git show 82e5b1f:benchmarks/bench_brax_backends.py`. Changing an entry changes the dynamics of every ID of that
# robot.
PHYSICS_BY_ROBOT: dict[str, str] = {
    "Walker": "mjx-newton-1-4",
    "Hopper": "mjx-newton-1-4",
    # not "mjx-newton-1-4-damp" (implicit Euler damping kept): under random actions 4.9% of 1024 environments go
    # non-finite within 3000 steps with it, 0% with "mjx-newton-1-4" (and with Brax as shipped, 11x slower).
    # Measured with `git show 82e5b1f:benchmarks/brax_stability_check.py` (run in that tree with
    # `--envs HalfCheetah-V-v0 --physics mjx-newton-1-4-damp mjx-newton-1-4 mjx`; 1024 environments × 3000 steps by
    # default), H200.
    "HalfCheetah": "mjx-newton-1-4",
    "Ant": "mjx-newton-1-4",
}

_INSTALL_HINT = 'pip install "pobax-bench[mujoco]"'


def _import_brax():
    try:
        import brax.envs
        import mujoco
        from mujoco import mjx
    except ImportError as e:
        raise ImportError(
            f"The masked MuJoCo environments need brax and mujoco-mjx, which are not installed "
            f"({e}). Install them with: {_INSTALL_HINT}"
        ) from e
    return brax.envs, mujoco, mjx


@functools.lru_cache(maxsize=None)
def load_brax_env(robot: str, physics: str) -> Any:
    """The raw Brax environment (no Brax wrappers) of `robot` under the physics setting `physics`.

    Cached: one Brax object per (robot, physics), so environments made twice are equal (same jit cache).
    """
    benvs, _, mjx = _import_brax()
    setting = PHYSICS[physics]
    env = benvs.get_environment(ROBOTS[robot].brax_name, backend=setting.backend)
    if setting.newton_iterations is not None:
        if setting.backend != "mjx":
            raise ValueError(f"Solver settings apply to the 'mjx' backend only, got {setting}.")
        flags, eulerdamp = int(env.sys.opt.disableflags), int(mjx.DisableBit.EULERDAMP)
        flags = (flags & ~eulerdamp) if setting.euler_damping else (flags | eulerdamp)
        env.sys = env.sys.tree_replace(
            {
                "opt.solver": mjx.SolverType.NEWTON,
                "opt.iterations": setting.newton_iterations,
                "opt.ls_iterations": setting.ls_iterations,
                "opt.disableflags": mjx.DisableBit(int(flags)),
            }
        )
    return env


def _strong(tree: PyTree) -> PyTree:
    # Brax mixes Python floats into its state (e.g. a constant healthy reward), which come back weakly typed
    # after `step` but not after `reset`: make every leaf strongly typed so that a jitted step compiles once
    # and `lax.scan` carries keep their types.
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.asarray(x).dtype), tree)


class BraxState(eqx.Module):
    """The state of a Brax environment: Brax's own `State` (MJX data in `inner.pipeline_state`)."""

    inner: PyTree[Array]


class BraxEnv(AbstractEnvironment[BraxState]):
    """A Brax robot whose observation is masked to positions (`P`), velocities (`V`) or left full (`F`).

    `observability="partial"` shows the mask, `"full"` the whole Brax observation. See the module docstring
    for the kept indices of each robot.
    """

    robot: str = eqx.field(static=True)
    mask: str = eqx.field(static=True)
    observability: str = eqx.field(static=True)
    physics: str = eqx.field(static=True)
    mask_layout: str = eqx.field(static=True)
    brax_env: Any = eqx.field(static=True)

    observabilities = ("partial", "full")

    def __init__(self, robot: str, mask: str, observability: str = "partial", physics: str | None = None,
                 mask_layout: str = "pobax"):
        if robot not in ROBOTS:
            raise ValueError(f"Unknown robot {robot!r}; expected one of {', '.join(ROBOTS)}.")
        if mask not in MASKS:
            raise ValueError(f"Unknown mask {mask!r}; expected one of {', '.join(MASKS)} (full, pos, vel).")
        if observability not in self.observabilities:
            raise ValueError(
                f"Masked MuJoCo has observabilities {self.observabilities}, got {observability!r}."
            )
        physics = PHYSICS_BY_ROBOT[robot] if physics is None else physics
        if physics not in PHYSICS:
            raise ValueError(
                f"Unknown physics setting {physics!r}; expected one of {', '.join(PHYSICS)} "
                f"(leave it unset for the pinned {PHYSICS_BY_ROBOT[robot]!r})."
            )
        if mask_layout not in MASK_LAYOUTS:
            raise ValueError(f"Unknown mask_layout {mask_layout!r}; expected one of {', '.join(MASK_LAYOUTS)}.")
        if mask_layout == "original" and robot not in ORIGINAL_MASKS:
            raise ValueError(
                f"mask_layout='original' is known for {', '.join(ORIGINAL_MASKS)} only, not {robot}; leave it unset."
            )
        self.robot = robot
        self.mask = mask
        self.observability = observability
        self.physics = physics
        self.mask_layout = mask_layout
        self.brax_env = load_brax_env(robot, physics)

    @property
    def spec(self) -> Robot:
        return ROBOTS[self.robot]

    @property
    def visible(self) -> tuple[int, ...]:
        """The indices of Brax's observation the agent sees, in order."""
        if self.observability == "full" or self.mask == "F":
            return tuple(range(self.spec.obs_size))
        if self.mask_layout == "original":
            return ORIGINAL_MASKS[self.robot][self.mask]
        if self.mask == "P":
            return tuple(range(self.spec.num_pos))
        return tuple(range(self.spec.num_pos, self.spec.obs_size))

    @property
    def observation_names(self) -> tuple[str, ...]:
        """What each entry of the observation is (see the module docstring)."""
        names = self.spec.pos_names + self.spec.vel_names
        return tuple(names[i] for i in self.visible)

    @property
    def gamma(self) -> float:
        return 0.99

    @property
    def observation_space(self) -> Box:
        return Box(-float("inf"), float("inf"), (len(self.visible),))

    @property
    def action_space(self) -> Box:
        return Box(-1.0, 1.0, (self.spec.action_size,))

    def observe(self, state: BraxState) -> Float[Array, " obs"]:
        """The agent's observation of a state: the visible entries of Brax's observation."""
        index = self.visible
        start = index[0]
        if index == tuple(range(start, start + len(index))):  # contiguous: a slice, no gather
            return state.inner.obs[start:start + len(index)].astype(jnp.float32)
        return state.inner.obs[jnp.asarray(index)].astype(jnp.float32)

    def _timestep(self, inner: Any, reward, terminated) -> TimeStep:
        state = BraxState(inner)
        # Brax's metrics (forward reward, x velocity, ...) have the same keys after reset and step.
        info = {k: jnp.asarray(v, jnp.float32) for k, v in inner.metrics.items()}
        return timestep(self.observe(state), reward, terminated, info=info)

    def reset(self, *, key: PRNGKeyArray) -> tuple[BraxState, TimeStep]:
        # Brax's code trips `jax_numpy_rank_promotion="raise"`: allow it there only.
        with jax.numpy_rank_promotion("allow"):
            inner = _strong(self.brax_env.reset(key))
        return BraxState(inner), self._timestep(inner, 0.0, False)

    def step(
        self, state: BraxState, action: Float[Array, " action"], *, key: PRNGKeyArray
    ) -> tuple[BraxState, TimeStep]:
        del key  # the physics is deterministic
        action = jnp.clip(self.action_space.as_action(action), -1.0, 1.0)
        with jax.numpy_rank_promotion("allow"):
            inner = _strong(self.brax_env.step(state.inner, action))
        return BraxState(inner), self._timestep(inner, inner.reward, inner.done > 0.5)
