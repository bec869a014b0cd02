"""T-Maze (Bakker 2001), as specified in the paper's appendix.

Layout: a start cell (position 0), a hallway of `length` cells (positions 1..length) and a junction
(position length + 1). The goal is up or down with probability 1/2, drawn at reset.

Observation, 4 bits: (reward-up cue, reward-down cue, in hallway, at junction).
- `partial`: the cue bits are set only at the start cell. Start `(1,0,0,0)` or `(0,1,0,0)`; hallway
  `(0,0,1,0)`; junction `(0,0,0,1)`. Both cue values are visible at the start and never look like the hallway.
- `full`: the cue bits are set everywhere (`(1,0,1,0)` in the hallway of an up-maze, and so on).

Actions: 0 up, 1 right, 2 down, 3 left. Right/left move along the corridor (walls at both ends keep the
agent in place). Up/down do nothing except at the junction, where they end the episode (terminal) with
+4 for the side of the goal and -0.1 for the other. All other rewards are 0.

The optimal discounted return is `4 * gamma ** (length + 1)` (length + 1 moves to the junction, the turn
is the (length + 2)-th action): 3.5814 for length 10. A memoryless policy cannot tell the sides apart at the
junction and earns at most `0.5 * (4 - 0.1) * gamma ** (length + 1)` = 1.746 for length 10.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ._base import AbstractEnvironment, TimeStep, timestep
from ._spaces import Box, Discrete

UP, RIGHT, DOWN, LEFT = 0, 1, 2, 3


class TMazeState(eqx.Module):
    pos: Int[Array, ""]
    goal_up: Bool[Array, ""]


class TMaze(AbstractEnvironment[TMazeState]):
    """T-Maze with a hallway of `length` cells between the start cell and the junction."""

    length: int = eqx.field(static=True)
    observability: str = eqx.field(static=True, default="partial")

    observabilities = ("partial", "full")

    def __check_init__(self):
        if not 1 <= self.length <= 2**31 - 3:  # positions 0 .. length + 1 are int32
            raise ValueError(f"T-Maze needs a hallway length in [1, 2**31 - 3], got {self.length}.")
        if self.observability not in self.observabilities:
            raise ValueError(
                f"T-Maze has observabilities {self.observabilities}, got {self.observability!r}."
            )

    @property
    def gamma(self) -> float:
        return 0.99

    @property
    def observation_space(self) -> Box:
        return Box(0.0, 1.0, (4,))

    @property
    def action_space(self) -> Discrete:
        return Discrete(4)

    @property
    def junction(self) -> int:
        return self.length + 1

    def optimal_return(self) -> float:
        """Discounted return of the optimal policy."""
        return 4.0 * self.gamma ** (self.length + 1)

    def memoryless_return(self) -> float:
        """Discounted return of the best memoryless policy (a coin flip at the junction)."""
        return 0.5 * (4.0 - 0.1) * self.gamma ** (self.length + 1)

    def observe(self, state: TMazeState) -> Float[Array, "4"]:
        at_start = state.pos == 0
        at_junction = state.pos == self.junction
        in_hallway = ~(at_start | at_junction)
        show_cue = at_start if self.observability == "partial" else jnp.asarray(True)
        up = show_cue & state.goal_up
        down = show_cue & ~state.goal_up
        return jnp.stack([up, down, in_hallway, at_junction]).astype(jnp.float32)

    def reset(self, *, key: PRNGKeyArray) -> tuple[TMazeState, TimeStep]:
        state = TMazeState(pos=jnp.zeros((), jnp.int32), goal_up=jax.random.bernoulli(key))
        return state, timestep(self.observe(state))

    def step(self, state: TMazeState, action: Int[Array, ""], *, key: PRNGKeyArray):
        del key  # deterministic
        action = self.action_space.as_action(action)
        at_junction = state.pos == self.junction
        move = jnp.where(action == RIGHT, 1, jnp.where(action == LEFT, -1, 0))
        pos = jnp.clip(state.pos + move, 0, self.junction).astype(jnp.int32)
        turned = at_junction & ((action == UP) | (action == DOWN))
        correct = (action == UP) == state.goal_up
        reward = jnp.where(turned, jnp.where(correct, 4.0, -0.1), 0.0)
        new_state = TMazeState(pos=pos, goal_up=state.goal_up)
        return new_state, timestep(self.observe(new_state), reward, terminated=turned)
