"""RockSample(n, k) (Smith & Simmons 2004), as specified in the paper's appendix.

An `n × n` grid holds `k` rocks at fixed cells (a property of the environment instance, see "Maps"). Each
episode draws every rock's goodness i.i.d. with probability 1/2 and the agent's start cell uniformly over
the grid. Positions are `(row, col)`, row 0 at the top; the exit is beyond the east edge.

Actions (`5 + k`): 0 north, 1 east, 2 south, 3 west, 4 sample, `5 + i` check rock `i`.
- A move into a wall leaves the agent in place, except east from the last column: the agent exits (+10,
  terminal).
- Sampling on a rock gives +10 if it is good (it then becomes bad) and -10 if it is bad; sampling on an empty
  cell does nothing.
- Checking rock `i` reports its true goodness with probability `½ (1 + 2^(-d / d_max))`, `d` the Euclidean
  distance from the agent to the rock and `d_max = √2 (n - 1)` the largest distance in the grid: always
  right at distance 0, right 3/4 of the time at distance `d_max`. `half_efficiency_distance` replaces `d_max`
  (the original implementation's sensor uses 20 for both sizes, `docs/parity.md`).
gamma 0.99; the registry adds a 1000-step time limit.

Observation (`2n + k`, float): the two-hot position (one-hot row, then one-hot column), then one entry per
rock, +1 "looks good", -1 "looks bad", 0 "no information". A check observes what the sensor reported; a
sample observes the rock as it is afterwards (bad).
- `partial`: the rock entries are non-zero only on the step that checked or sampled that rock;
- `perfect_memory` (the paper's "full observation space" for RockSample): each rock entry keeps its most
  recent observation;
- `full`: the rock entries are the true goodness of every rock (±1).

Maps: rock cells are distinct and come from `map_seed` through a pure-Python SplitMix64 generator (a partial
Fisher-Yates shuffle of the `n²` cells), so a map never changes with the JAX version or its PRNG. The default
maps (`map_seed=0`) of RockSample(11, 11) and RockSample(15, 15) are also written out as constants below
(`DEFAULT_MAPS`); a test checks that the generator reproduces them. Pass `rock_positions` for a custom map.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from .._paths import shown
from ._base import AbstractEnvironment, TimeStep, timestep
from ._spaces import Box, Discrete

NORTH, EAST, SOUTH, WEST, SAMPLE = 0, 1, 2, 3, 4
#: Rewards (Smith & Simmons): leaving by the east edge, sampling a good rock; a bad one costs as much.
EXIT_REWARD, SAMPLE_REWARD = 10.0, 10.0
_MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1], [0, 0]], np.int32)  # row/col deltas; last: no move

# map_seed=0 maps, (row, col) per rock, as `rock_positions_from_seed(n, k, 0)` draws them.
DEFAULT_MAPS: dict[tuple[int, int], tuple[tuple[int, int], ...]] = {
    (11, 11): (
        (7, 1), (5, 6), (1, 0), (5, 2), (0, 8), (2, 1), (0, 9), (7, 10), (2, 8), (5, 8), (7, 9),
    ),
    (15, 15): (
        (10, 10), (9, 14), (8, 7), (1, 4), (5, 11), (5, 0), (11, 8), (10, 5),
        (6, 10), (3, 2), (9, 11), (2, 3), (1, 3), (3, 7), (2, 5),
    ),
}

_MASK64 = (1 << 64) - 1


def _splitmix64(seed: int):
    state = seed & _MASK64
    while True:
        state = (state + 0x9E3779B97F4A7C15) & _MASK64
        z = state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
        yield z ^ (z >> 31)


def rock_positions_from_seed(size: int, num_rocks: int, seed: int) -> tuple[tuple[int, int], ...]:
    """`num_rocks` distinct cells of a `size × size` grid, drawn by a version-independent generator."""
    if not 0 < num_rocks <= size * size:
        raise ValueError(f"RockSample needs 1..{size * size} rocks on a {size}x{size} grid, got {num_rocks}.")
    n, moved, rocks = size * size, {}, []  # a Fisher-Yates shuffle's first num_rocks swaps, over the cells it moved
    rng = _splitmix64(seed)
    for i in range(num_rocks):
        j = i + next(rng) % (n - i)  # modulo bias < n² / 2^64: negligible
        moved[i], moved[j] = moved.get(j, j), moved.get(i, i)
        rocks.append(moved[i])
    return tuple(divmod(c, size) for c in rocks)


#: The most rocks a RockSample takes: each adds an action and a feature of the observation (the paper's: 11 and 15).
MAX_ROCKS = 2**16


class RockSampleState(eqx.Module):
    pos: Int[Array, "2"]  # (row, col)
    rock_good: Bool[Array, " rocks"]
    rock_obs: Float[Array, " rocks"]  # most recent observation of each rock: +1 good, -1 bad, 0 none yet
    observed: Int[Array, ""]  # the rock checked or sampled on the last step, -1 if none


class RockSample(AbstractEnvironment[RockSampleState]):
    """RockSample on a `size × size` grid with `num_rocks` rocks at `rock_positions`."""

    size: int = eqx.field(static=True)
    num_rocks: int = eqx.field(static=True)
    observability: str = eqx.field(static=True)
    map_seed: int | None = eqx.field(static=True)  # None for a custom `rock_positions`
    half_efficiency_distance: float | None = eqx.field(static=True)  # None: the paper's d_max
    rock_positions: Int[Array, "rocks 2"]

    observabilities = ("partial", "perfect_memory", "full")

    def __init__(
        self,
        size: int,
        num_rocks: int,
        observability: str = "partial",
        map_seed: int | None = 0,
        rock_positions: tuple[tuple[int, int], ...] | None = None,
        half_efficiency_distance: float | int | None = None,
    ):
        if not 2 <= size <= 46340 or not 1 <= num_rocks <= MAX_ROCKS:  # cell indices (size² of them) are int32
            raise ValueError(f"RockSample needs a size in [2, 46340] and 1 to {MAX_ROCKS:,} rocks (its actions and "
                             f"observation grow with them), got ({size}, {num_rocks}).")
        if observability not in self.observabilities:
            raise ValueError(f"RockSample has observabilities {self.observabilities}, got {observability!r}.")
        if rock_positions is None:
            if map_seed is None:
                raise ValueError("RockSample needs a `map_seed` or explicit `rock_positions`; got neither.")
            if isinstance(map_seed, bool) or not isinstance(map_seed, (int, np.integer)) \
                    or not 0 <= map_seed <= _MASK64:  # the generator's state is 64 bits: others would alias
                raise ValueError(f"RockSample's map_seed must be an integer in [0, 2**64 - 1], got {map_seed!r}.")
            rock_positions = DEFAULT_MAPS.get((size, num_rocks)) if map_seed == 0 else None
            if rock_positions is None:
                rock_positions = rock_positions_from_seed(size, num_rocks, map_seed)
        else:
            map_seed = None
        outside = ValueError(f"RockSample({size}, {num_rocks}) needs {num_rocks} (row, col) rock positions inside the "
                             f"grid (rock_positions: integers in [0, {size - 1}]); got {rock_positions}.")
        try:  # (a coordinate beyond int64, e.g. 2**63, is outside the grid too: not NumPy's OverflowError)
            positions = np.asarray(rock_positions, np.int64).reshape(-1, 2)
        except (OverflowError, ValueError, TypeError):
            raise outside from None
        if len(positions) != num_rocks or positions.min() < 0 or positions.max() >= size:
            raise outside  # (checked in int64: a coordinate beyond int32 is named, not NumPy's "out of bounds")
        positions = positions.astype(np.int32)
        if len({tuple(p) for p in positions.tolist()}) != num_rocks:
            raise ValueError(f"RockSample rocks must be on distinct cells; got {rock_positions}.")
        if half_efficiency_distance is not None:
            d0 = half_efficiency_distance
            number = isinstance(d0, (int, float, np.integer, np.floating)) and not isinstance(d0, bool)
            try:  # an int beyond a float's range (10**400) is out of range, not an OverflowError
                d0 = float(d0) if number else None
            except OverflowError:
                d0 = None
            if d0 is None or not np.finfo(np.float32).tiny <= d0 <= np.finfo(np.float32).max:
                raise ValueError(f"RockSample's half_efficiency_distance must be a positive float32 number, "
                                 f"{np.finfo(np.float32).tiny:.3g} to {np.finfo(np.float32).max:.3g} (the sensor "
                                 f"divides by it in float32; None: the paper's √2 (size - 1)), got "
                                 f"{shown(half_efficiency_distance)}.")
            half_efficiency_distance = float(d0)
        self.half_efficiency_distance = half_efficiency_distance
        self.size, self.num_rocks = size, num_rocks
        self.observability, self.map_seed = observability, map_seed
        self.rock_positions = jnp.asarray(positions)

    @property
    def gamma(self) -> float:
        return 0.99

    def exit_at_once_return(self) -> float:
        """Discounted return of walking east to the exit without checking or sampling a rock: a policy that ignores
        its observation, and where RockSample agents that stop exploring settle. From start column `c` it earns
        10 γ^(n - 1 - c); the start column is uniform, so the mean is 10 (1 - γ^n) / (n (1 - γ)): 9.515 for n = 11,
        9.329 for n = 15."""
        return EXIT_REWARD * (1.0 - self.gamma ** self.size) / (self.size * (1.0 - self.gamma))

    @property
    def max_distance(self) -> float:
        """The sensor's half-efficiency distance: the paper's largest distance in the grid, or the constructor's."""
        return self.half_efficiency_distance or math.sqrt(2.0) * (self.size - 1)

    @property
    def observation_space(self) -> Box:
        return Box(-1.0, 1.0, (2 * self.size + self.num_rocks,))

    @property
    def action_space(self) -> Discrete:
        return Discrete(5 + self.num_rocks)

    def check_accuracy(self, pos: Int[Array, "2"]) -> Float[Array, " rocks"]:
        """Probability that checking each rock from `pos` reports its true goodness."""
        d = jnp.linalg.norm((self.rock_positions - pos[None, :]).astype(jnp.float32), axis=-1)
        return 0.5 * (1.0 + jnp.exp2(-d / self.max_distance))

    def observe(self, state: RockSampleState) -> Float[Array, " obs"]:
        row = jax.nn.one_hot(state.pos[0], self.size, dtype=jnp.float32)
        col = jax.nn.one_hot(state.pos[1], self.size, dtype=jnp.float32)
        if self.observability == "partial":
            rocks = jnp.where(jnp.arange(self.num_rocks) == state.observed, state.rock_obs, 0.0)
        elif self.observability == "perfect_memory":
            rocks = state.rock_obs
        else:
            rocks = jnp.where(state.rock_good, 1.0, -1.0)
        return jnp.concatenate([row, col, rocks])

    def reset(self, *, key: PRNGKeyArray) -> tuple[RockSampleState, TimeStep]:
        k_pos, k_good = jax.random.split(key)
        cell = jax.random.randint(k_pos, (), 0, self.size * self.size)
        state = RockSampleState(
            pos=jnp.stack([cell // self.size, cell % self.size]).astype(jnp.int32),
            rock_good=jax.random.bernoulli(k_good, 0.5, (self.num_rocks,)),
            rock_obs=jnp.zeros((self.num_rocks,), jnp.float32),
            observed=jnp.asarray(-1, jnp.int32),
        )
        return state, timestep(self.observe(state))

    def step(
        self, state: RockSampleState, action: Int[Array, ""], *, key: PRNGKeyArray
    ) -> tuple[RockSampleState, TimeStep]:
        action = self.action_space.as_action(action)
        valid = (action >= 0) & (action < 5 + self.num_rocks)  # an action outside the action space changes nothing
        col = state.pos[1]
        # Moves (walls clip), and the exit east of the last column.
        delta = jnp.where(valid, jnp.asarray(_MOVES)[jnp.clip(action, 0, SAMPLE)], 0)
        pos = jnp.clip(state.pos + delta, 0, self.size - 1)
        exited = (action == EAST) & (col == self.size - 1)
        # Sampling the rock under the agent (if any).
        at = jnp.all(self.rock_positions == state.pos[None, :], axis=-1)  # (no size² table: any size fits)
        here = jnp.where(at.any(), jnp.argmax(at), -1)
        sampled = (action == SAMPLE) & (here >= 0)
        here_good = state.rock_good[jnp.maximum(here, 0)]
        rock_good = state.rock_good.at[jnp.maximum(here, 0)].set(here_good & ~sampled)
        # Checking rock i: the sensor is right with a probability that decays with distance.
        checked = valid & (action >= 5)
        i = jnp.clip(action - 5, 0, self.num_rocks - 1)
        right = jax.random.uniform(key) < self.check_accuracy(state.pos)[i]
        looks_good = jnp.where(right, state.rock_good[i], ~state.rock_good[i])
        observed = jnp.where(checked, i, jnp.where(sampled, here, -1))
        value = jnp.where(checked & looks_good, 1.0, -1.0)  # after a sample the rock is bad
        slot = jnp.maximum(observed, 0)
        rock_obs = state.rock_obs.at[slot].set(jnp.where(observed >= 0, value, state.rock_obs[slot]))

        sample_reward = jnp.where(sampled, jnp.where(here_good, SAMPLE_REWARD, -SAMPLE_REWARD), 0.0)
        reward = EXIT_REWARD * exited.astype(jnp.float32) + sample_reward
        new_state = RockSampleState(pos=pos, rock_good=rock_good, rock_obs=rock_obs, observed=observed)
        return new_state, timestep(self.observe(new_state), reward, terminated=exited)
