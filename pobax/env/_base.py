"""The environment contract.

Every environment is an unbatched `eqx.Module`: one environment, one state. Batching over environments,
seeds and hyperparameters is `jax.vmap` from outside. An environment *is* its parameters: sizes that set
shapes are static fields, numbers are array leaves.
"""

from typing import Any, Generic, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray, PyTree

from ._spaces import AbstractSpace

S = TypeVar("S")


class TimeStep(eqx.Module):
    """What an environment returns from `reset` and `step`.

    - `obs`: the observation after this step. After an auto-reset it is the first observation of the new
      episode; the last observation of the episode that just ended is then in `final_obs`.
    - `terminated`: the episode ended in a terminal state; its value is zero (do not bootstrap).
    - `truncated`: the episode was cut by a time limit; bootstrap from the value of `final_obs`.
    - `final_obs`: set by `AutoReset`; `None` for an environment without auto-reset (then it equals `obs`).
    - `info`: extra per-step quantities (e.g. achievements); the structure must not depend on the step.

    Environments return unbatched time steps (scalar reward and flags); a vmapped environment returns the same
    structure with a leading batch axis, hence the `*batch` annotations.
    """

    obs: PyTree[Array]
    reward: Float[Array, "*batch"]
    terminated: Bool[Array, "*batch"]
    truncated: Bool[Array, "*batch"]
    final_obs: PyTree[Array] = None
    info: dict[str, Any] = eqx.field(default_factory=dict)

    @property
    def done(self) -> Bool[Array, "*batch"]:
        return jnp.logical_or(self.terminated, self.truncated)


def timestep(obs, reward=0.0, terminated=False, truncated=False, info=None) -> TimeStep:
    """Build a `TimeStep` with the canonical dtypes (float32 reward, bool flags)."""
    return TimeStep(
        obs=obs,
        reward=jnp.asarray(reward, jnp.float32),
        terminated=jnp.asarray(terminated, bool),
        truncated=jnp.asarray(truncated, bool),
        info={} if info is None else info,
    )


class AbstractEnvironment(eqx.Module, Generic[S]):
    """An environment: `reset(key=...)` and `step(state, action, key=...)`.

    Subclasses define `observation_space`, `action_space` and `gamma` (as fields or properties), and
    `max_steps_in_episode` (the time limit the registry applies; `None` for no limit).
    """

    @property
    def observation_space(self) -> AbstractSpace:
        raise NotImplementedError

    @property
    def action_space(self) -> AbstractSpace:
        raise NotImplementedError

    @property
    def gamma(self) -> float:
        raise NotImplementedError

    @property
    def max_steps_in_episode(self) -> int | None:
        return None

    @property
    def episode_metrics(self) -> dict[str, tuple[str, ...]]:
        """Entries of `TimeStep.info` that training logs per episode: info key → one column name per element
        of the entry's last axis. The entry's value on the step that ends an episode describes that episode
        (e.g. Craftax's achievements unlocked, 0/1); the logged figure is its mean over the episodes that ended
        in an update (a success rate for 0/1 values)."""
        return {}

    @property
    def unwrapped(self) -> "AbstractEnvironment":
        return self

    def reset(self, *, key: PRNGKeyArray) -> tuple[S, TimeStep]:
        raise NotImplementedError

    def step(self, state: S, action: Array, *, key: PRNGKeyArray) -> tuple[S, TimeStep]:
        """One step from `state` with `action` (an integer array of shape () for a `Discrete` space). An action of
        the wrong kind (a float, bool or string, or a batch: `AbstractSpace.as_action`) is refused with a ValueError
        when the step is traced. A discrete action outside the action space (a step under `jit` cannot refuse it) is
        never read as another action: it does nothing (T-Maze, RockSample and the mazes: the agent stays; Craftax:
        its NOOP; Battleship: a wasted shot, -1)."""
        raise NotImplementedError


class AbstractWrapper(AbstractEnvironment[S]):
    """A wrapper holds an inner environment and forwards what it does not change."""

    env: eqx.AbstractVar[AbstractEnvironment]

    @property
    def observation_space(self) -> AbstractSpace:
        return self.env.observation_space

    @property
    def action_space(self) -> AbstractSpace:
        return self.env.action_space

    @property
    def gamma(self) -> float:
        return self.env.gamma

    @property
    def max_steps_in_episode(self) -> int | None:
        return self.env.max_steps_in_episode

    @property
    def episode_metrics(self) -> dict[str, tuple[str, ...]]:
        return self.env.episode_metrics

    @property
    def unwrapped(self) -> AbstractEnvironment:
        return self.env.unwrapped


def action_mask(obs: PyTree[Array]) -> Bool[Array, "..."] | None:
    """The action mask carried by an observation (a dict with an `"action_mask"` entry), if any."""
    if isinstance(obs, dict) and "action_mask" in obs:
        return obs["action_mask"]
    return None


def observation_array(obs: PyTree[Array]) -> Array:
    """The observation proper, without an action mask."""
    if isinstance(obs, dict):
        return obs["obs"]
    return obs


SEED_MAX = 2**32 - 1


def check_seed(seed: int, flag: str = "--seed") -> None:
    """A ValueError naming `flag` unless `seed` is an integer in [0, 2**32 - 1]: seeds are 32-bit, and JAX would
    take a negative one as another seed's bits, or overflow on a larger one."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed <= SEED_MAX:
        raise ValueError(f"{flag} must be an integer in [0, {SEED_MAX}] (seeds are 32-bit), got {seed}.")


def random_rollout(env: AbstractEnvironment, num_steps: int, key, capture):
    """`capture(state, obs)` of `env`'s first `num_steps` states under uniformly random actions (the state after
    reset, then one per action), stacked along a leading axis, and the `num_steps - 1` actions. Unbatched and
    traceable: `jax.jit` it with `env` and `capture` closed over."""
    if not 1 <= num_steps <= 2**31 - 1:  # a scan's length is an int32
        raise ValueError(f"random_rollout: num_steps must be an integer in [1, 2**31 - 1], got {num_steps:,}.")
    k_reset, k_steps = jax.random.split(key)
    state, ts = env.reset(key=k_reset)

    def body(carry, k):
        state, obs = carry
        k_act, k_step = jax.random.split(k)
        action = env.action_space.sample(k_act)
        view = capture(state, obs)
        state, ts = env.step(state, action, key=k_step)
        return (state, ts.obs), (view, action)

    keys = jax.random.split(k_steps, max(num_steps - 1, 0))
    (state, obs), (views, actions) = jax.lax.scan(body, (state, ts.obs), keys)
    last = capture(state, obs)
    return jax.tree.map(lambda v, w: jnp.concatenate([v, w[None]]), views, last), actions

