"""Small environments the tests build agents on (`test_ppo.py`, `test_hostile_api.py`)."""

import jax.numpy as jnp

import pobax.env as E


class ConstantReward(E.AbstractEnvironment):
    """`reward` every step and a constant observation; never terminates (`length` None: with a time limit, V = 1 /
    (1 - γ) when truncation bootstraps, much less if a time limit were treated as terminal), else terminates after
    `length` steps. `discount`: γ."""

    reward: float = 1.0
    discount: float = 0.9
    length: int | None = None

    @property
    def observation_space(self):
        return E.Box(0.0, 1.0, (2,))

    @property
    def action_space(self):
        return E.Discrete(2)

    @property
    def gamma(self):
        return self.discount

    def reset(self, *, key):
        return jnp.zeros((), jnp.int32), E.timestep(jnp.ones((2,), jnp.float32))

    def step(self, state, action, *, key):
        state = state + 1
        ended = False if self.length is None else state >= self.length
        return state, E.timestep(jnp.ones((2,), jnp.float32), self.reward, terminated=ended)
