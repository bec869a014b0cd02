"""DeepMind Lab mazes on NAVIX: `Navix-DMLab-Maze-{01,02,03}-v0` (paper appendix "DeepMind Lab MiniGrid mazes").

The layouts are the entity layers of DeepMind Lab's `nav_maze_random_goal_0{1,2,3}` levels (shipped in
`pobax/env/data/dmlab_mazes.txt`): 11 x 21, 19 x 31 and 27 x 41 cells with 109, 318 and 668 free cells.
Every episode draws the start cell, the start direction and the goal cell uniformly, start != goal (the
goal uniform among the other free cells). Entering the goal cell gives +1 and ends the episode (terminal);
all other rewards are 0; gamma = 0.99. The registry cuts episodes at 2000 / 4000 / 6000 steps.

Actions (MiniGrid's first three, as NAVIX's `MINIGRID_ACTION_SET`): 0 rotate left (counter-clockwise),
1 rotate right (clockwise), 2 forward (blocked by walls). Directions as NAVIX: 0 east, 1 south, 2 west,
3 north; positions are (row, column).

Dynamics are NAVIX's: each step lifts the small pobax state into a `navix.states.State` over the maze grid,
applies NAVIX's MiniGrid action functions through `navix.transitions.deterministic_transition`, and reads
reward and termination from NAVIX's goal-reached event (`navix.rewards/terminations.on_goal_reached`).
pobax owns reset sampling (NAVIX's `random_positions` draws with replacement, so start could equal goal)
and the observation functions. A full NAVIX `Environment` is not used as the state: it carries the grid
and an RGB rendering cache per environment (44 KB for maze 01, 212 KB for maze 03) that `vmap` and the
auto-reset `where` would copy every step, and it has its own auto-reset and time limit, which pobax's
wrappers provide.

Observations (one-hot, as bool: the encoders cast them to float32, and a rollout buffer of the full view holds a
quarter of float32's bytes; channels (wall, goal); outside the grid counts as wall):
- `partial`, shape (2, 3, 2): the 2 x 3 cells in front of the agent, rotated with it as in MiniGrid's
  egocentric view (the agent looks "up" the image). Row 0 is two cells ahead, row 1 the cell directly
  ahead; columns are left, straight, right. The agent's own cell is not shown (it is never a wall, and
  never the goal while an episode runs). Cell `[i, j]` = position + (2 - i) * ahead + (j - 1) * right.
- `perfect_memory`, shape (12 + 2h + 2w + 4,): the `partial` view flattened, then one-hots of the agent's row (h),
  column (w) and direction (4), then of the goal's row (h) and column (w). Not the paper's: what an agent with the
  same view knows once it has localised itself and found the goal (the layout never changes, so this is a Markov
  state), in at most 17 active inputs where `full` has thousands. A ceiling of the paper's kind (its section
  "Results": a ceiling is what an agent with its original observations should reach if it mitigates partial
  observability): it sees everything the floor sees. The benchmark's maze ceilings read it (on the map maze 02's
  learned nothing; docs/deviations.md).
- `full`, shape (2h - 1, 2w - 1, 6): the whole maze shifted so that the agent is at the centre
  `[h - 1, w - 1]` (not rotated), wall and goal channels, then the one-hot facing direction broadcast over
  4 channels.
"""

import functools
import importlib.resources

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int, PRNGKeyArray

from ._base import AbstractEnvironment, TimeStep, timestep
from ._maze_oracle import DIRECTION_DELTAS, free_cells
from ._spaces import Box, Discrete

MAZE_IDS = ("01", "02", "03")
MAX_STEPS = {"01": 2000, "02": 4000, "03": 6000}
# Exact shortest-path oracle over all (start, direction, goal) triples, start != goal, gamma = 0.99:
# `_maze_oracle.oracle_values` (tests/test_dmlab_maze.py recomputes them).
ORACLE_VALUES = {
    "01": {"optimal_discounted_return": 0.7711119886331972, "optimal_mean_episode_length": 28.434760448521917},
    "02": {"optimal_discounted_return": 0.6590026657822473, "optimal_mean_episode_length": 45.711163026010354},
    "03": {"optimal_discounted_return": 0.5203643447845503, "optimal_mean_episode_length": 75.37497306735854},
}
# The uniformly random policy (actions 0-2 with equal probability) under the registry's time limit, mean over the
# episodes that ended, as the training logs average: `random_policy(maze, num_envs=256, steps=12000)` of
# `tests/test_dmlab_maze.py` (seed 0; its slow test measures them again; 95% CIs: 01 [0.067, 0.079], 02 [0.028, 0.042],
# 03 [0.014, 0.039]; benchmarks/results/maze02-ceiling-h200x2.json). An agent at this level has learned nothing.
RANDOM_POLICY_VALUES = {
    "01": {"random_policy_discounted_return": 0.0728, "random_policy_undiscounted_return": 0.384},
    "02": {"random_policy_discounted_return": 0.0349, "random_policy_undiscounted_return": 0.300},
    "03": {"random_policy_discounted_return": 0.0255, "random_policy_undiscounted_return": 0.238},
}

# Partial view offsets for each direction: [direction, row, column] -> (d_row, d_column).
_RIGHT = DIRECTION_DELTAS[[1, 2, 3, 0]]  # clockwise of each direction
_VIEW_OFFSETS = (
    np.arange(2, 0, -1)[None, :, None, None] * DIRECTION_DELTAS[:, None, None, :]
    + np.arange(-1, 2)[None, None, :, None] * _RIGHT[:, None, None, :]
).astype(np.int32)  # (4, 2, 3, 2)


def _navix():
    """Import NAVIX on first use, so that pobax works without the extra."""
    try:
        import navix  # noqa: F401
        from navix import actions, entities, rendering, rewards, states, terminations, transitions  # noqa: F401
    except ImportError as e:
        raise ImportError(
            "The DMLab mazes (Navix-DMLab-Maze-*) need NAVIX, which is not installed. "
            'Install it with `pip install "pobax-bench[navix]"`.'
        ) from e
    return navix


@functools.cache
def load_layouts() -> dict[str, str]:
    """The maze layouts from the shipped data file, by id: '*' wall, ' ' free cell."""
    text = importlib.resources.files("pobax.env").joinpath("data/dmlab_mazes.txt").read_text()
    layouts, current, lines = {}, None, []
    for line in text.splitlines() + [""]:
        if line.startswith("== "):
            current, lines = line[3:].strip(), []
        elif current is not None and line.strip() == "":
            layouts[current], current = "\n".join(lines), None
        elif current is not None:
            lines.append(line)
    return layouts


def parse_layout(layout: str) -> np.ndarray:
    """A layout ('*' wall, anything else free) as a boolean wall map; ragged rows are padded with walls."""
    rows = [r for r in layout.split("\n") if r.strip()]
    width = max(len(r) for r in rows)
    return np.array([[c == "*" for c in r.ljust(width, "*")] for r in rows], dtype=bool)


#: The longest side, in cells, of a maze's layout: 25 times the largest DMLab maze's (27 x 41). The wall map is padded
#: by its longer side on every side and the `full` view is (2h - 1) x (2w - 1) x 6 per environment and step, so both
#: grow as the square of the side (a 3 x 100,000 layout asked for 56 GiB at construction).
MAX_LAYOUT_SIDE = 1024


def _shown(layout: str, most: int = 60) -> str:
    """`layout` for a one-line message: its repr (newlines as \\n), cut to `most` characters."""
    text = repr(layout)
    return text if len(text) <= most else f"{text[:most]}... ({len(layout):,} characters)"


def check_layout(layout: str) -> None:
    """A one-line ValueError naming the option unless `layout` is a string of rows of at most `MAX_LAYOUT_SIDE` cells,
    at most `MAX_LAYOUT_SIDE` of them, with at least one that is not blank."""
    if not isinstance(layout, str):
        raise ValueError(f"A maze's layout is a string of rows ('*' wall, anything else free, rows separated by "
                         f"newlines), got {type(layout).__name__}.")
    rows = [r for r in layout.split("\n") if r.strip()]
    if not rows:
        raise ValueError(f"A maze's layout has no rows (only blank lines), got {_shown(layout)}; give rows of '*' "
                         f"(wall) and ' ' (free), enclosed by walls.")
    height, width = len(rows), max(len(r) for r in rows)
    if max(height, width) > MAX_LAYOUT_SIDE:
        raise ValueError(f"A maze's layout is {height:,} x {width:,} cells, more than {MAX_LAYOUT_SIDE:,} a side (its "
                         f"padded wall map and full view grow as the square of the side); give a smaller layout.")


class DMLabMazeState(eqx.Module):
    position: Int[Array, "2"]  # (row, column)
    direction: Int[Array, ""]  # 0 east, 1 south, 2 west, 3 north
    goal: Int[Array, "2"]


class DMLabMaze(AbstractEnvironment[DMLabMazeState]):
    """A DeepMind Lab maze (`maze_id` "01", "02", "03") or any enclosed `layout`, with MiniGrid dynamics."""

    walls: Bool[Array, "h w"]
    padded_walls: Bool[Array, "ph pw"]  # walls with a border of `pad` wall cells on each side
    free: Int[Array, "f 2"]  # free cells, (row, column)
    maze_id: str = eqx.field(static=True)
    observability: str = eqx.field(static=True)
    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    pad: int = eqx.field(static=True)

    observabilities = ("partial", "perfect_memory", "full")

    def __init__(self, maze_id: str = "01", observability: str = "partial", *, layout: str | None = None):
        _navix()  # fail at construction, not inside a trace
        if layout is None:
            if maze_id not in MAZE_IDS:
                raise ValueError(f"Expected a DMLab maze id in {MAZE_IDS}, got {maze_id!r}.")
            layout = load_layouts()[maze_id]
        else:
            maze_id = "custom"
        if observability not in self.observabilities:
            raise ValueError(
                f"DMLab maze has observabilities {self.observabilities}, got {observability!r}."
            )
        check_layout(layout)
        walls = parse_layout(layout)
        free = free_cells(walls)
        if len(free) < 2:
            raise ValueError(f"A maze needs at least 2 free cells (start != goal), this layout has {len(free)}.")
        if not (walls[0].all() and walls[-1].all() and walls[:, 0].all() and walls[:, -1].all()):
            raise ValueError(f"Expected a layout enclosed by walls ('*' on every border cell), got {_shown(layout)}; "
                             f"add a border of walls around it.")
        self.maze_id, self.observability = maze_id, observability
        self.height, self.width = walls.shape
        self.pad = max(self.height, self.width)
        self.walls = jnp.asarray(walls)
        self.padded_walls = jnp.asarray(np.pad(walls, self.pad, constant_values=True))
        self.free = jnp.asarray(free)

    @property
    def num_free(self) -> int:
        return self.free.shape[0]

    @property
    def gamma(self) -> float:
        return 0.99

    @property
    def max_steps_in_episode(self) -> int | None:
        return MAX_STEPS.get(self.maze_id)

    @property
    def action_space(self) -> Discrete:
        return Discrete(3)

    @property
    def observation_space(self) -> Box:
        if self.observability == "partial":
            return Box(0.0, 1.0, (2, 3, 2), jnp.bool_)
        if self.observability == "perfect_memory":
            return Box(0.0, 1.0, (12 + 2 * self.height + 2 * self.width + 4,), jnp.bool_)
        return Box(0.0, 1.0, (2 * self.height - 1, 2 * self.width - 1, 6), jnp.bool_)

    def observe(self, state: DMLabMazeState) -> Bool[Array, "..."]:
        if self.observability == "partial":
            return self._partial_view(state)
        if self.observability == "perfect_memory":
            return self._pose_view(state)
        return self._full_view(state)

    def _pose_view(self, state: DMLabMazeState) -> Bool[Array, " n"]:
        h, w = self.height, self.width
        parts = (self._partial_view(state).reshape(-1),
                 jnp.arange(h) == state.position[0], jnp.arange(w) == state.position[1],
                 jnp.arange(4) == state.direction,
                 jnp.arange(h) == state.goal[0], jnp.arange(w) == state.goal[1])
        return jnp.concatenate(parts)

    def _partial_view(self, state: DMLabMazeState) -> Bool[Array, "2 3 2"]:
        cells = state.position[None, None, :] + jnp.asarray(_VIEW_OFFSETS)[state.direction]  # (2, 3, 2)
        wall = self.padded_walls[cells[..., 0] + self.pad, cells[..., 1] + self.pad]
        goal = jnp.all(cells == state.goal[None, None, :], axis=-1)
        return jnp.stack([wall, goal], axis=-1)

    def _full_view(self, state: DMLabMazeState) -> Bool[Array, "hh ww 6"]:
        h, w = self.height, self.width
        r, c = state.position[0], state.position[1]
        # Maze cell (i, j) appears at (i - r + h - 1, j - c + w - 1): the agent lands on the centre.
        wall = jax.lax.dynamic_slice(
            self.padded_walls, (r + self.pad - (h - 1), c + self.pad - (w - 1)), (2 * h - 1, 2 * w - 1)
        )
        goal_row = jnp.arange(2 * h - 1) == state.goal[0] - r + h - 1
        goal_col = jnp.arange(2 * w - 1) == state.goal[1] - c + w - 1
        goal = goal_row[:, None] & goal_col[None, :]
        facing = jnp.broadcast_to(jax.nn.one_hot(state.direction, 4, dtype=bool), (2 * h - 1, 2 * w - 1, 4))
        return jnp.concatenate([wall[..., None], goal[..., None], facing], axis=-1)

    def reset(self, *, key: PRNGKeyArray) -> tuple[DMLabMazeState, TimeStep]:
        k_start, k_goal, k_dir = jax.random.split(key, 3)
        start = jax.random.randint(k_start, (), 0, self.num_free)
        # Uniform over the other free cells: draw among num_free - 1 and skip the start.
        goal = jax.random.randint(k_goal, (), 0, self.num_free - 1)
        goal = jnp.where(goal >= start, goal + 1, goal)
        state = DMLabMazeState(
            position=self.free[start],
            direction=jax.random.randint(k_dir, (), 0, 4, dtype=jnp.int32),
            goal=self.free[goal],
        )
        return state, timestep(self.observe(state))

    def _navix_step(self, state: DMLabMazeState, action: Int[Array, ""], key: PRNGKeyArray):
        navix = _navix()
        ent = navix.entities
        # NAVIX's own code relies on rank promotion; keep the check for pobax's code only.
        with jax.numpy_rank_promotion("allow"):
            nstate = navix.states.State(
                key=key,
                grid=jnp.where(self.walls, -1, 0).astype(jnp.int32),
                # Movement never renders; an empty cache keeps NAVIX from building RGB tiles.
                cache=navix.rendering.cache.RenderingCache(patches=jnp.zeros((1, 1, 1, 3), jnp.uint8)),
                entities={
                    ent.Entities.PLAYER: ent.Player.create(
                        position=state.position,
                        direction=state.direction,
                        pocket=navix.components.EMPTY_POCKET_ID,
                    )[None],
                    ent.Entities.GOAL: ent.Goal.create(position=state.goal, probability=jnp.asarray(1.0))[None],
                },
            )
            action_set = navix.actions.MINIGRID_ACTION_SET[:3]  # rotate_ccw, rotate_cw, forward
            new = navix.transitions.deterministic_transition(nstate, action, action_set)
            reward = navix.rewards.on_goal_reached(nstate, action, new)
            reached = navix.terminations.on_goal_reached(nstate, action, new)
            player = new.get_player(idx=0)
        position = jnp.asarray(player.position, jnp.int32)
        direction = jnp.asarray(player.direction, jnp.int32)
        return DMLabMazeState(position, direction, state.goal), reward, reached

    def step(
        self, state: DMLabMazeState, action: Int[Array, ""], *, key: PRNGKeyArray
    ) -> tuple[DMLabMazeState, TimeStep]:
        action = self.action_space.as_action(action)
        new_state, reward, reached = self._navix_step(state, action, key)
        valid = (action >= 0) & (action < self.action_space.n)  # an action outside the action space: the agent stays
        new_state = jax.tree.map(lambda a, b: jnp.where(valid, a, b), new_state, state)
        reward, reached = jnp.where(valid, reward, 0.0), valid & reached
        return new_state, timestep(self.observe(new_state), reward, terminated=reached)
