"""Wrappers: time limit, auto-reset, previous-action concatenation.

Wrappers hold an inner environment and never subclass it. The registry composes them as
`AutoReset(ActionConcat(TimeLimit(env)))`: the time limit counts the raw environment's steps, the previous
action is appended to whatever observation the observability variant produced, and auto-reset sits
outermost so that `final_obs` is in exactly the space the agent sees (needed to bootstrap a truncated
episode from the value of its final observation).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Int, PRNGKeyArray, PyTree

from ._base import AbstractEnvironment, AbstractWrapper, TimeStep
from ._spaces import Box, DictSpace, Discrete


def tree_select(pred, on_true: PyTree, on_false: PyTree) -> PyTree:
    """`jnp.where(pred, a, b)` leaf by leaf, for a scalar `pred`."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


class TimeLimitState(eqx.Module):
    env_state: PyTree
    t: Int[Array, ""]


class TimeLimit(AbstractWrapper[TimeLimitState]):
    """Cuts episodes after `max_steps` steps: `truncated` is set, `terminated` is left as it is."""

    env: AbstractEnvironment
    max_steps: int = eqx.field(static=True)

    def __check_init__(self):
        if self.max_steps < 1:
            raise ValueError(f"TimeLimit needs max_steps >= 1, got {self.max_steps}.")

    @property
    def max_steps_in_episode(self) -> int:
        return self.max_steps

    def reset(self, *, key: PRNGKeyArray) -> tuple[TimeLimitState, TimeStep]:
        s, ts = self.env.reset(key=key)
        return TimeLimitState(s, jnp.zeros((), jnp.int32)), ts

    def step(self, state: TimeLimitState, action: Array, *, key: PRNGKeyArray):
        s, ts = self.env.step(state.env_state, action, key=key)
        t = state.t + 1
        truncated = jnp.logical_or(ts.truncated, jnp.logical_and(t >= self.max_steps, ~ts.terminated))
        return TimeLimitState(s, t), eqx.tree_at(lambda x: x.truncated, ts, truncated)


class AutoReset(AbstractWrapper):
    """Starts a new episode as soon as one ends.

    On the step that ends an episode, `obs` is the first observation of the next episode and `final_obs`
    the last observation of the one that ended; `reward`, `terminated` and `truncated` belong to the
    episode that ended. The next `step` therefore acts in the new episode: no junk transition is added.
    """

    env: AbstractEnvironment

    def reset(self, *, key: PRNGKeyArray):
        s, ts = self.env.reset(key=key)
        return s, eqx.tree_at(lambda x: x.final_obs, ts, ts.obs, is_leaf=lambda x: x is None)

    def step(self, state, action: Array, *, key: PRNGKeyArray):
        k_step, k_reset = jax.random.split(key)
        s, ts = self.env.step(state, action, key=k_step)
        s0, ts0 = self.env.reset(key=k_reset)
        done = ts.done
        return tree_select(done, s0, s), TimeStep(
            obs=tree_select(done, ts0.obs, ts.obs),
            reward=ts.reward,
            terminated=ts.terminated,
            truncated=ts.truncated,
            final_obs=ts.obs,
            info=ts.info,
        )


def _append_action(obs: Array, action_features: Array) -> Array:
    if jnp.issubdtype(obs.dtype, jnp.integer):
        # uint8 images are scaled to [0, 1] first (as the encoders would), so actions in [-1, 1] survive
        obs = obs.astype(jnp.float32) / 255.0
    if obs.ndim == 1:
        return jnp.concatenate([obs, action_features.astype(obs.dtype)])
    # Images (H, W, C): the action becomes extra channels, constant over the image.
    planes = jnp.broadcast_to(action_features.astype(obs.dtype), obs.shape[:-1] + action_features.shape)
    return jnp.concatenate([obs, planes], axis=-1)


class ActionConcat(AbstractWrapper):
    """Appends the previous action to the observation (one-hot for discrete actions; zeros at reset).

    Applied after any observation masking or observability variant, so the agent really sees it. For
    image observations the action is appended as extra constant channels; a uint8 image is first scaled to
    float32 in [0, 1] (what the encoders do with uint8), so that actions in [-1, 1] are not cast to uint8.
    """

    env: AbstractEnvironment

    def _features(self, action: Array) -> Array:
        space = self.env.action_space
        if isinstance(space, Discrete):
            return jax.nn.one_hot(action, space.n, dtype=jnp.float32)
        return jnp.reshape(action, (-1,)).astype(jnp.float32)

    def _num_features(self) -> int:
        space = self.env.action_space
        if isinstance(space, Discrete):
            return space.n
        return math.prod(space.shape)  # static: a Python int, never traced

    def _with_action(self, obs: PyTree, action_features: Array) -> PyTree:
        if isinstance(obs, dict):
            return {**obs, "obs": _append_action(obs["obs"], action_features)}
        return _append_action(obs, action_features)

    @property
    def observation_space(self):
        inner = self.env.observation_space
        box = inner["obs"] if isinstance(inner, DictSpace) else inner
        shape = box.shape[:-1] + (box.shape[-1] + self._num_features(),)
        if jnp.issubdtype(box.dtype, jnp.integer):  # uint8 images become float32 in [0, 1] (`_append_action`)
            new = Box(-1.0, 1.0, shape, jnp.float32)
        else:
            new = Box(min(box.low, -1.0), max(box.high, 1.0), shape, box.dtype)
        if isinstance(inner, DictSpace):
            return DictSpace({**inner.spaces, "obs": new})
        return new

    def reset(self, *, key: PRNGKeyArray):
        s, ts = self.env.reset(key=key)
        zeros = jnp.zeros((self._num_features(),), jnp.float32)
        return s, eqx.tree_at(lambda x: x.obs, ts, self._with_action(ts.obs, zeros))

    def step(self, state, action: Array, *, key: PRNGKeyArray):
        s, ts = self.env.step(state, action, key=key)
        return s, eqx.tree_at(lambda x: x.obs, ts, self._with_action(ts.obs, self._features(action)))
