"""Hostile values of the environments' constructor options (`--env-options KEY=VALUE`, `make(env_id, **options)`):
each is refused in one line naming the option and its range, at construction, never by a traceback deep inside a
library, an out-of-memory, a reset that searches for minutes or a step that overflows. Environments are constructed,
not trained (the CLI cases are refused before anything compiles)."""

import jax
import numpy as np
import pytest

from _hostile import TINY, refused
from pobax.env import make


def refusal(env_id: str, observability: str = "partial", **options) -> str:
    """The one-line ValueError `make(env_id, observability, **options)` raises."""
    with pytest.raises(ValueError) as e:
        make(env_id, observability, **options)
    message = str(e.value)
    assert "\n" not in message and len(message) < 600, message
    return message


ROCKS = [[0, 0], [0, 1], [0, 2], [0, 3]]


@pytest.mark.parametrize("coordinate", [2**31, 10**12, 2**63])
def test_rock_positions_beyond_int32_or_int64_are_named_as_outside_the_grid(coordinate):
    """Were "Python integer 2147483648 out of bounds for int32" and "Python int too large to convert to C long":
    NumPy's words, naming neither the option nor its range."""
    message = refusal("rocksample_5_5", rock_positions=[*ROCKS, [coordinate, 0]])
    assert "rock_positions: integers in [0, 4]" in message and str(coordinate) in message, message


def test_rock_positions_inside_the_grid_still_build():
    env = make("rocksample_5_5", rock_positions=[*ROCKS, [4, 4]], wrappers=False)
    assert np.asarray(env.rock_positions).dtype == np.int32
    assert np.asarray(env.rock_positions).tolist()[-1] == [4, 4]


def test_a_half_efficiency_distance_beyond_a_float_is_out_of_range_not_an_overflow():
    """10**400 was "int too large to convert to float" (an OverflowError comparing it with float32's largest)."""
    message = refusal("rocksample_5_5", half_efficiency_distance=10**400)
    assert "half_efficiency_distance must be a positive float32 number" in message, message
    assert "an integer of about 401 digits" in message, message
    assert "an integer of about 5,001 digits" in refusal("rocksample_5_5", half_efficiency_distance=10**5000)
    assert make("rocksample_5_5", half_efficiency_distance=3, wrappers=False).max_distance == 3.0


@pytest.mark.parametrize("ships, message", [
    # 0 or 1 of 131,072 proposals legal (by the draws): each reset searched for seconds to hours (50 ones on 10x10: 70 s a reset)
    ([2] * 25, "random placements of them are legal (at least 4 needed)"),
    ([3] * 16, "crowd a 10x10 board"),
    # 50 ships: 1,225 overlap checks per proposal, 28 s to compile the reset alone (and 70 s a reset)
    ([1] * 50, "Battleship takes at most 32 ships"),
    ([1] * 33, "Battleship takes at most 32 ships"),
])
def test_a_fleet_whose_legal_placements_are_too_rare_to_sample_is_refused_at_construction(ships, message):
    assert message in refusal("battleship_10", ship_lengths=ships)


def test_crowded_but_samplable_fleets_still_build_and_reset():
    """Ten ships of 5 on 10x10 (2 in 10,000 proposals legal) reset in a few hundred rounds: still allowed; 32 ships
    (the most) on a board where they fit easily, too."""
    env = make("battleship_10", "full", ship_lengths=[5] * 10, wrappers=False)
    state, _ = jax.jit(lambda k: env.reset(key=k))(jax.random.key(0))
    assert np.bincount(np.asarray(state.ships)[np.asarray(state.ships) >= 0]).tolist() == [5] * 10
    make("battleship_40", ship_lengths=[1] * 32, wrappers=False)


@pytest.mark.parametrize("layout", ["", "\n\n", "   \n  \t "])
def test_a_maze_layout_without_rows_is_refused_by_name(layout):
    """Was "max() arg is an empty sequence"."""
    pytest.importorskip("navix")
    message = refusal("Navix-DMLab-Maze-01-v0", layout=layout)
    assert "A maze's layout has no rows" in message, message


def test_a_maze_layout_not_enclosed_is_refused_in_one_line():
    """The message printed the whole layout over several lines (a 1,000-row layout: 1,000 lines of error)."""
    pytest.importorskip("navix")
    message = refusal("Navix-DMLab-Maze-01-v0", layout="* *\n* *\n***")
    assert "Expected a layout enclosed by walls" in message and "'* *\\n* *\\n***'" in message, message
    message = refusal("Navix-DMLab-Maze-01-v0", layout="\n".join(["* " * 400] * 400))
    assert "(320,399 characters)" in message, message


@pytest.mark.parametrize("height, width", [(3, 1025), (1025, 3), (3, 100_000)])
def test_a_maze_layout_too_large_to_hold_is_refused_before_any_array(height, width):
    """A 3 x 100,000 layout asked NumPy for 56 GiB at construction (its wall map padded by the longer side on every
    side): a MemoryError, or the OOM killer; the full view of a 1,025-cell side is 2,049 x 2,049 x 6 per step."""
    pytest.importorskip("navix")
    rows = ["*" * width] + ["*" + " " * (width - 2) + "*"] * (height - 2) + ["*" * width]
    message = refusal("Navix-DMLab-Maze-01-v0", layout="\n".join(rows))
    assert f"{height:,} x {width:,} cells, more than 1,024 a side" in message, message


def test_a_maze_layout_of_the_largest_side_still_builds():
    pytest.importorskip("navix")
    rows = ["*" * 1024, "*" + " " * 1022 + "*", "*" * 1024]
    env = make("Navix-DMLab-Maze-01-v0", layout="\n".join(rows), wrappers=False)
    assert (env.height, env.width, env.num_free) == (3, 1024, 1022)


@pytest.mark.parametrize("steps", [2**31, 10**12, 2**63])
def test_a_craftax_time_limit_beyond_int32_is_refused_at_construction(steps):
    """Was built, then an OverflowError from inside the first jitted step ("An overflow was encountered while parsing
    an argument to a jitted computation")."""
    message = refusal("craftax_pixels", "full", max_timesteps=steps)
    assert f"max_timesteps must be an integer in [1, 2**31 - 1] (steps, counted in int32), got {steps}" in message


@pytest.mark.parametrize("env, option, message", [
    ("rocksample_5_5", f"rock_positions=[[0,0],[0,1],[0,2],[0,3],[{2**63},0]]", "integers in [0, 4]"),
    ("Navix-DMLab-Maze-01-v0", "layout=", "A maze's layout has no rows"),
    ("battleship_10", f"ship_lengths={[2] * 25}".replace(" ", ""), "crowd a 10x10 board"),
])
def test_the_cli_refuses_them_in_one_line_with_exit_2_and_no_run_directory(tmp_path, capsys, env, option, message):
    if env.startswith("Navix"):
        pytest.importorskip("navix")
    refused(capsys, ["train", "--env", env, *TINY[2:], "--env-options", option, "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()
