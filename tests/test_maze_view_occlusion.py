"""benchmarks/maze_view_occlusion.py: its views are the environment's, and its occlusion rules hide what they say."""

import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("navix")

from pobax.env import DMLabMaze  # noqa: E402
from pobax.env._dmlab_maze import DMLabMazeState  # noqa: E402

_spec = importlib.util.spec_from_file_location(
    "maze_view_occlusion", Path(__file__).parent.parent / "benchmarks" / "maze_view_occlusion.py")
occlusion = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(occlusion)


def test_views_are_the_environments_partial_observations():
    env = DMLabMaze("01")
    walls, free = np.asarray(env.walls), np.asarray(env.free)
    poses = np.array([(r, c, d) for r, c in free[:40] for d in range(4)], np.int64)
    observe = jax.jit(jax.vmap(lambda p: env.observe(DMLabMazeState(position=p[:2], direction=p[2],
                                                                    goal=jnp.asarray(free[-1])))))
    expected = np.asarray(observe(jnp.asarray(poses, jnp.int32)))[..., 0]
    np.testing.assert_array_equal(occlusion.views(walls, poses), expected)


def _view(rows):
    return np.array([[[c == "#" for c in row] for row in rows]])


@pytest.mark.parametrize("rule", occlusion.RULES)
def test_a_wall_row_ahead_hides_the_row_behind_it(rule):
    np.testing.assert_array_equal(occlusion.occlude(_view(["...", "###"]), rule), _view(["###", "###"]))
    open_view = _view(["...", "..."])
    np.testing.assert_array_equal(occlusion.occlude(open_view, rule), open_view)  # nothing hidden
    one_ahead = _view(["#.#", "..."])
    np.testing.assert_array_equal(occlusion.occlude(one_ahead, rule), one_ahead)  # the row ahead is always seen


def test_the_rules_differ_where_minigrid_sees_diagonally():
    view = _view(["...", ".#."])  # only the cell straight ahead is a wall
    np.testing.assert_array_equal(occlusion.occlude(view, "line"), _view([".#.", ".#."]))
    np.testing.assert_array_equal(occlusion.occlude(view, "minigrid"), view)  # seen past it through the sides
    # sight spreads along the row two ahead from the open right side, up to the wall two ahead in the centre
    np.testing.assert_array_equal(occlusion.occlude(_view(["...", "##."]), "minigrid"), _view(["...", "##."]))
    np.testing.assert_array_equal(occlusion.occlude(_view([".#.", "##."]), "minigrid"), _view(["##.", "##."]))
