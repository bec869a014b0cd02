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
import numpy as np
from jaxtyping import Array, Int, PRNGKeyArray, PyTree

from .._modules import map_modules, replace_static
from ._base import AbstractEnvironment, AbstractWrapper, TimeStep
from ._spaces import Box, DictSpace, Discrete


def tree_select(pred, on_true: PyTree, on_false: PyTree) -> PyTree:
    """`jnp.where(pred, a, b)` leaf by leaf, for a scalar `pred`."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def check_key(key, where: str) -> None:
    """A TypeError naming `where` unless `key` is a JAX random key (`jax.random.key(0)`, or the raw uint32 key data
    of `jax.random.PRNGKey(0)`): JAX's own error for `key=0` does not say which argument it was."""
    if not isinstance(key, jax.Array | np.ndarray):
        raise TypeError(f"{where}: key must be a JAX random key, e.g. jax.random.key(0), got {type(key).__name__} "
                        f"{key!r}.")


class TimeLimitState(eqx.Module):
    env_state: PyTree
    t: Int[Array, ""]


class TimeLimit(AbstractWrapper[TimeLimitState]):
    """Cuts episodes after `max_steps` steps: `truncated` is set, `terminated` is left as it is."""

    env: AbstractEnvironment
    max_steps: int = eqx.field(static=True)

    def __check_init__(self):  # the step counter is int32
        m = self.max_steps
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= 2**31 - 1:
            raise ValueError(f"time_limit must be an integer in [1, 2**31 - 1] (steps), got {m!r}.")

    @property
    def max_steps_in_episode(self) -> int:
        return self.max_steps

    def reset(self, *, key: PRNGKeyArray) -> tuple[TimeLimitState, TimeStep]:
        check_key(key, "reset")
        s, ts = self.env.reset(key=key)
        return TimeLimitState(s, jnp.zeros((), jnp.int32)), ts

    def step(self, state: TimeLimitState, action: Array, *, key: PRNGKeyArray):
        check_key(key, "step")
        s, ts = self.env.step(state.env_state, action, key=key)
        t = state.t + 1
        truncated = jnp.logical_or(ts.truncated, jnp.logical_and(t >= self.max_steps, ~ts.terminated))
        return TimeLimitState(s, t), eqx.tree_at(lambda x: x.truncated, ts, truncated)


def _select_reset(env: AbstractEnvironment, done, key, state, obs):
    """`(state, obs)` with done environments replaced by `env.reset(key=key)`: every environment is reset and
    the reset is selected where `done` (under `vmap` a `lax.cond` would become this select anyway)."""
    s0, ts0 = env.reset(key=key)
    return tree_select(done, s0, state), tree_select(done, ts0.obs, obs)


def _reset_done(env: AbstractEnvironment, pool_size: int, done, key, state, obs):
    """`(state, obs)` with done environments replaced by `env.reset(key=key)`, resetting only those.

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
            return jax.vmap(tree_select)(d, jax.vmap(reset_one)(dyn_env, k), (s, o)), out_batched

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


class AutoReset(AbstractWrapper):
    """Starts a new episode as soon as one ends.

    On the step that ends an episode, `obs` is the first observation of the next episode and `final_obs`
    the last observation of the one that ended; `reward`, `terminated`, `truncated` and `info` belong to the
    episode that ended. The next `step` therefore acts in the new episode: no junk transition is added.

    The step key is split into `(k_step, k_reset)` and a done environment's new episode is
    `env.reset(key=k_reset)`. How the resets are computed is `pool_size`:

    - `None` (default): every environment computes a reset on every step and keeps it where done (cheap
      resets: T-Maze; RockSample and Battleship on accelerators).
    - `P`: only done environments are reset, P at a time (`_reset_done`): under `vmap` over N environments a
      `while_loop` generates P resets per round for the next P done environments until all have one; a step
      where none is done resets nothing. For expensive resets (Craftax world generation). Same keys, same
      episodes as `None`, bit for bit (`tests/test_wrappers.py`); only the cost differs. Larger P suits
      accelerators (a round of P costs about one), small P CPUs. The registry uses P = 8 for Craftax everywhere
      and for RockSample and Battleship on the CPU (`_families.pooled_auto_reset`).

    `pool_by_platform`: `for_backend` replaces `pool_size` by the platform's (`pobax._backend.reset_pool_size`).
    """

    env: AbstractEnvironment
    pool_size: int | None = eqx.field(static=True, default=None)
    pool_by_platform: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.pool_size is not None and self.pool_size < 1:
            raise ValueError(f"pool_size must be >= 1 or None, got {self.pool_size}.")

    def reset(self, *, key: PRNGKeyArray):
        check_key(key, "reset")
        s, ts = self.env.reset(key=key)
        return s, eqx.tree_at(lambda x: x.final_obs, ts, ts.obs, is_leaf=lambda x: x is None)

    def step(self, state, action: Array, *, key: PRNGKeyArray):
        check_key(key, "step")
        k_step, k_reset = jax.random.split(key)
        s, ts = self.env.step(state, action, key=k_step)
        if self.pool_size is None:
            s_next, obs = _select_reset(self.env, ts.done, k_reset, s, ts.obs)
        else:
            s_next, obs = _reset_done(self.env, self.pool_size, ts.done, k_reset, s, ts.obs)
        return s_next, TimeStep(
            obs=obs,
            reward=ts.reward,
            terminated=ts.terminated,
            truncated=ts.truncated,
            final_obs=ts.obs,
            info=ts.info,
        )


def _uint8_planes(obs_dtype, obs_ndim: int, one_hot: bool) -> bool:
    """Whether the action is appended to an integer image as integer planes of 0/255 (a one-hot action:
    exactly 0/1 after the encoders' scaling by 1/255; Craftax's 43 planes in float32 would make a 128-step
    rollout of 2048 environments 43 GB, in uint8 a quarter of that)."""
    return one_hot and obs_ndim == 3 and jnp.issubdtype(obs_dtype, jnp.integer)


def _append_action(obs: Array, action_features: Array, one_hot: bool) -> Array:
    if obs.dtype == jnp.bool_:
        # one-hot grids (the DMLab mazes) stay bool with a one-hot action; a continuous action needs floats
        obs = obs if one_hot else obs.astype(jnp.float32)
    if _uint8_planes(obs.dtype, obs.ndim, one_hot):
        planes = jnp.broadcast_to((action_features * 255).astype(obs.dtype), obs.shape[:-1] + action_features.shape)
        return jnp.concatenate([obs, planes], axis=-1)
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

    `applied`: a continuous action as the environment applies it, clipped to the action space's bounds (the masked
    and pixel MuJoCo robots clip to [-1, 1]); False (the default), as the agent gave it: a Gaussian policy's sample,
    whose spread is unbounded. Discrete actions are the same either way.

    Applied after any observation masking or observability variant, so the agent really sees it. For
    image observations the action is appended as extra constant channels. A uint8 image with a discrete
    action stays uint8 (one-hot planes of 0/255, which the encoders scale to 0/1 like the image); with a
    continuous action it is first scaled to float32 in [0, 1] (what the encoders do with uint8), so that
    actions in [-1, 1] are not cast to uint8. A bool grid (the DMLab mazes) with a discrete action stays bool.
    """

    env: AbstractEnvironment
    applied: bool = eqx.field(static=True, default=False)

    def _features(self, action: Array) -> Array:
        space = self.env.action_space
        if self._one_hot:
            return jax.nn.one_hot(action, space.n, dtype=jnp.float32)
        action = jnp.reshape(action, (-1,)).astype(jnp.float32)
        return jnp.clip(action, space.low, space.high) if self.applied else action

    def _num_features(self) -> int:
        space = self.env.action_space
        if self._one_hot:
            return space.n
        return math.prod(space.shape)  # static: a Python int, never traced

    @property
    def _one_hot(self) -> bool:
        return isinstance(self.env.action_space, Discrete)

    def _with_action(self, obs: PyTree, action_features: Array) -> PyTree:
        if isinstance(obs, dict):
            return {**obs, "obs": _append_action(obs["obs"], action_features, self._one_hot)}
        return _append_action(obs, action_features, self._one_hot)

    @property
    def observation_space(self):
        inner = self.env.observation_space
        box = inner["obs"] if isinstance(inner, DictSpace) else inner
        shape = box.shape[:-1] + (box.shape[-1] + self._num_features(),)
        if _uint8_planes(box.dtype, len(shape), self._one_hot):
            new = Box(box.low, box.high, shape, box.dtype)  # one-hot planes of 0/255
        elif box.dtype == jnp.bool_ and self._one_hot:  # a one-hot action appended to a bool grid
            new = Box(0.0, 1.0, shape, box.dtype)
        elif jnp.issubdtype(box.dtype, jnp.integer) or box.dtype == jnp.bool_:  # become float32 (`_append_action`)
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


def for_backend(env: AbstractEnvironment, backend) -> AbstractEnvironment:
    """`env` with the implementation choices of `backend` (a `pobax._backend.Backend`, resolved from the devices
    that run it): the pool size of every `AutoReset` with `pool_by_platform`, and `loop_free` where it was left to
    the platform (Battleship's placement sampling). The same episodes whatever the choices; only speed differs.
    Training does this once, where it builds its programs (`pobax.agent.Runs`)."""
    def configure(m):
        if isinstance(m, AutoReset) and m.pool_by_platform:
            return replace_static(m, pool_size=backend.pool_size())
        if "loop_free" in m.__dataclass_fields__ and m.loop_free is None:
            return replace_static(m, loop_free=backend.loop_free())
        return m

    return map_modules(configure, env)
