"""Shortest-path oracle for MiniGrid-style mazes with the actions (rotate left, rotate right, forward).

The oracle knows the maze, its position, direction and the goal, and takes a shortest path. Its mean
discounted return over the episode distribution (start cell, direction and goal uniform, start != goal) is
the "best possible" line of the DMLab-maze plots. Everything is exact: the shortest number of actions from
every (start, direction) to every goal is computed by value iteration over the state graph cell x direction
(a breadth-first search run for all goals at once, in numpy), then averaged over all triples.

Conventions are NAVIX's (and MiniGrid's): direction 0 east (column + 1), 1 south (row + 1), 2 west, 3 north;
action 0 rotates counter-clockwise (left), 1 clockwise (right), 2 moves one cell forward unless the cell
ahead is a wall. Reaching the goal cell ends the episode with reward 1; an episode of `T` actions is worth
`gamma ** (T - 1)`.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int

# (row, column) change of one forward step for each direction, as `navix.grid.translate`.
DIRECTION_DELTAS = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int32)
LEFT, RIGHT, FORWARD = 0, 1, 2

_UNREACHED = np.iinfo(np.int32).max // 2


def free_cells(walls: np.ndarray) -> np.ndarray:
    """The free cells of a maze as (row, column) pairs, in row-major order: shape (num_free, 2)."""
    return np.argwhere(~np.asarray(walls, bool)).astype(np.int32)


def shortest_distances(walls: np.ndarray) -> np.ndarray:
    """Shortest number of actions to reach each goal: `dist[goal, start, direction]`.

    `goal` and `start` index `free_cells(walls)`; `dist[g, g, :]` is 0. Unreachable pairs (a maze in several
    pieces) get a very large value. The maze must be enclosed by walls (every border cell a wall).
    """
    walls = np.asarray(walls, bool)
    if walls.ndim != 2 or not (walls[0].all() and walls[-1].all() and walls[:, 0].all() and walls[:, -1].all()):
        raise ValueError(
            f"Expected a 2D wall map enclosed by walls (every border cell a wall), got shape {walls.shape}; "
            "add a border of walls around the layout."
        )
    cells = free_cells(walls)
    num = len(cells)
    index = np.full(walls.shape, -1, np.int64)
    index[cells[:, 0], cells[:, 1]] = np.arange(num)
    # Successor of a forward step: the cell ahead if it is free, otherwise the agent stays where it is.
    ahead = cells[:, None, :] + DIRECTION_DELTAS[None, :, :]  # (num, 4, 2)
    ahead_index = index[ahead[..., 0], ahead[..., 1]]
    forward = np.where(ahead_index >= 0, ahead_index, np.arange(num)[:, None])  # (num, 4)
    # Layout [start, direction, goal] keeps the gathers below contiguous; int16 halves the memory traffic
    # (a shortest path visits each (cell, direction) at most once, so it is shorter than 4 * num).
    dtype = np.int16 if 4 * num < np.iinfo(np.int16).max // 2 else np.int32
    unreached = np.iinfo(dtype).max // 2
    dist = np.full((num, 4, num), unreached, dtype)
    dist[np.arange(num), :, np.arange(num)] = 0
    dirs = np.arange(4)
    # Value iteration on the deterministic graph; each sweep extends all shortest paths by one action, so
    # it ends after (longest shortest path + 1) sweeps.
    while True:
        succ = np.minimum(
            np.minimum(dist[:, (dirs + 3) % 4], dist[:, (dirs + 1) % 4]), dist[forward, dirs[None, :]]
        )
        new = np.minimum(dist, succ + 1)
        if np.array_equal(new, dist):
            break
        dist = new
    dist = dist.transpose(2, 0, 1).astype(np.int32)
    return np.where(dist >= unreached, _UNREACHED, dist)


def oracle_values(walls: np.ndarray, gamma: float) -> dict[str, float]:
    """Exact mean discounted return and mean episode length of the oracle, over all (start, direction,
    goal) triples with start != goal, each equally likely."""
    dist = shortest_distances(walls).astype(np.float64)
    off_diagonal = ~np.eye(dist.shape[0], dtype=bool)
    steps = dist[off_diagonal]  # (num * (num - 1), 4)
    if steps.max() >= _UNREACHED:
        raise ValueError("Some goal cannot be reached from some start: the maze has disconnected parts.")
    return {
        "optimal_discounted_return": float(np.mean(gamma ** (steps - 1))),
        "optimal_mean_episode_length": float(np.mean(steps)),
    }


class MazeOracle(eqx.Module):
    """A jittable shortest-path policy: `oracle(position, direction, goal) -> action`.

    Takes the action whose successor state is closest to the goal (ties: left, then right, then forward).
    """

    walls: Bool[Array, "h w"]
    cell_index: Int[Array, "h w"]  # index into the free cells, -1 on walls
    dist: Int[Array, "goals starts 4"]

    def __init__(self, walls: np.ndarray):
        walls = np.asarray(walls, bool)
        cells = free_cells(walls)
        index = np.full(walls.shape, -1, np.int32)
        index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
        self.walls = jnp.asarray(walls)
        self.cell_index = jnp.asarray(index)
        self.dist = jnp.asarray(shortest_distances(walls))

    def distance(
        self, position: Int[Array, "2"], direction: Int[Array, ""], goal: Int[Array, "2"]
    ) -> Int[Array, ""]:
        """Shortest number of actions from (position, direction) to the goal cell."""
        g = self.cell_index[goal[0], goal[1]]
        return self.dist[g, self.cell_index[position[0], position[1]], direction]

    def __call__(
        self, position: Int[Array, "2"], direction: Int[Array, ""], goal: Int[Array, "2"]
    ) -> Int[Array, ""]:
        g = self.cell_index[goal[0], goal[1]]
        here = self.cell_index[position[0], position[1]]
        ahead = position + jnp.asarray(DIRECTION_DELTAS)[direction]
        ahead_index = self.cell_index[ahead[0], ahead[1]]
        forward_index = jnp.where(ahead_index >= 0, ahead_index, here)
        candidates = jnp.stack(
            [
                self.dist[g, here, (direction + 3) % 4],
                self.dist[g, here, (direction + 1) % 4],
                self.dist[g, forward_index, direction],
            ]
        )
        return jnp.argmin(candidates).astype(jnp.int32)
