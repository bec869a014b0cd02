"""DMLab mazes on NAVIX (`Navix-DMLab-Maze-{01,02,03}-v0`) and the shortest-path oracle."""

import collections
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("navix")

import pobax.env as E  # noqa: E402
from pobax.env._dmlab_maze import (  # noqa: E402
    MAX_STEPS,
    ORACLE_VALUES,
    RANDOM_POLICY_VALUES,
    DMLabMaze,
    DMLabMazeState,
    _navix,
    load_layouts,
    parse_layout,
)
from pobax.env._maze_oracle import DIRECTION_DELTAS, MazeOracle, oracle_values, shortest_distances  # noqa: E402

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
LEFT, RIGHT, FORWARD = 0, 1, 2
TINY = "******\n*    *\n* ** *\n*    *\n******"


@pytest.fixture(scope="module")
def maze01():
    return DMLabMaze("01")


def place(position, direction, goal) -> DMLabMazeState:
    return DMLabMazeState(
        jnp.asarray(position, jnp.int32), jnp.asarray(direction, jnp.int32), jnp.asarray(goal, jnp.int32)
    )


def place_many(positions, directions, goals) -> DMLabMazeState:
    """A batch of hand-placed states (the state's fields are annotated unbatched)."""
    return jax.vmap(place)(jnp.asarray(positions), jnp.asarray(directions), jnp.asarray(goals))


def reference_step(walls, position, direction, action):
    """MiniGrid semantics, written independently of NAVIX and of pobax."""
    if action == LEFT:
        return position, (direction - 1) % 4
    if action == RIGHT:
        return position, (direction + 1) % 4
    ahead = (position[0] + DIRECTION_DELTAS[direction][0], position[1] + DIRECTION_DELTAS[direction][1])
    return (position if walls[ahead] else ahead), direction


def reference_view(walls, position, direction, goal):
    """The (2, 3, 2) view by rotating the padded map so that the agent faces up (MiniGrid's convention)."""
    marks = np.zeros(walls.shape, np.int8)
    marks[goal] = 1
    marks[position] = 2
    padded_walls = np.pad(walls, 2, constant_values=True)
    padded_marks = np.pad(marks, 2)
    k = (direction + 1) % 4  # np.rot90 turns counter-clockwise: east needs one turn to point up
    rw, rm = np.rot90(padded_walls, k), np.rot90(padded_marks, k)
    (r,), (c,) = np.nonzero(rm == 2)
    return np.stack([rw[r - 2 : r, c - 1 : c + 2], rm[r - 2 : r, c - 1 : c + 2] == 1], axis=-1).astype(np.float32)


def test_layouts_parse_to_documented_sizes():
    layouts = load_layouts()
    assert sorted(layouts) == ["01", "02", "03"]
    for maze_id, shape, num_free in [("01", (11, 21), 109), ("02", (19, 31), 318), ("03", (27, 41), 668)]:
        walls = parse_layout(layouts[maze_id])
        assert walls.shape == shape
        assert (~walls).sum() == num_free
        env = DMLabMaze(maze_id)
        assert (env.height, env.width, env.num_free) == (*shape, num_free)


def test_bad_layout_and_id_raise():
    with pytest.raises(ValueError, match="enclosed by walls"):
        DMLabMaze(layout="****\n*  *\n*   \n****")
    with pytest.raises(ValueError, match="maze id"):
        DMLabMaze("04")
    with pytest.raises(ValueError, match="observabilities"):
        DMLabMaze("01", "belief")


def test_missing_navix_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "navix", None)
    with pytest.raises(ImportError, match=r'pip install "pobax-bench\[navix\]"'):
        _navix()


@pytest.mark.parametrize(
    "position, direction, goal, walls, goals",
    [
        # Corner (1, 1): north and west see only walls (row -1 and column -1 are outside the grid).
        ((1, 1), NORTH, (9, 1), [[1, 1, 1], [1, 1, 1]], [[0, 0, 0], [0, 0, 0]]),
        ((1, 1), WEST, (9, 1), [[1, 1, 1], [1, 1, 1]], [[0, 0, 0], [0, 0, 0]]),
        ((1, 1), EAST, (1, 3), [[1, 0, 0], [1, 0, 1]], [[0, 1, 0], [0, 0, 0]]),
        ((1, 1), SOUTH, (3, 1), [[1, 0, 1], [1, 0, 1]], [[0, 1, 0], [0, 0, 0]]),
        # Bottom corridor (row 9); the goal directly ahead, then ahead-right, ahead-left.
        ((9, 10), EAST, (9, 11), [[1, 0, 1], [1, 0, 1]], [[0, 0, 0], [0, 1, 0]]),
        ((9, 7), WEST, (8, 5), [[1, 0, 0], [1, 0, 1]], [[0, 0, 1], [0, 0, 0]]),
        ((9, 5), NORTH, (7, 4), [[0, 0, 1], [1, 0, 1]], [[1, 0, 0], [0, 0, 0]]),
        ((7, 5), SOUTH, (9, 6), [[0, 0, 0], [1, 0, 1]], [[1, 0, 0], [0, 0, 0]]),
    ],
)
def test_hand_placed_views(maze01, position, direction, goal, walls, goals):
    obs = maze01.observe(place(position, direction, goal))
    assert obs.shape == (2, 3, 2) and obs.dtype == jnp.bool_ == maze01.observation_space.dtype
    np.testing.assert_array_equal(obs[..., 0], np.array(walls, np.float32))
    np.testing.assert_array_equal(obs[..., 1], np.array(goals, np.float32))


def test_views_match_rotated_map_everywhere(maze01):
    walls = np.asarray(maze01.walls)
    free = [tuple(int(v) for v in p) for p in np.asarray(maze01.free)]
    rng = np.random.default_rng(0)
    states = [(p, d, free[rng.integers(len(free))]) for p in free for d in range(4)]
    batch = place_many([s[0] for s in states], [s[1] for s in states], [s[2] for s in states])
    views = np.asarray(jax.jit(jax.vmap(maze01.observe))(batch))
    for (p, d, g), view in zip(states, views):
        np.testing.assert_array_equal(view, reference_view(walls, p, d, g), err_msg=f"{p=} {d=} {g=}")


def test_dynamics_follow_minigrid_semantics(maze01):
    walls = np.asarray(maze01.walls)
    step = jax.jit(lambda s, a, k: maze01.step(s, a, key=k))
    state, _ = maze01.reset(key=jax.random.key(3))
    rng = np.random.default_rng(1)
    position, direction = tuple(int(v) for v in state.position), int(state.direction)
    goal = tuple(int(v) for v in state.goal)
    blocked = 0
    for i in range(300):
        action = int(rng.choice(3, p=[0.2, 0.2, 0.6]))
        expected = reference_step(walls, position, direction, action)
        blocked += action == FORWARD and expected[0] == position
        state, ts = step(state, jnp.int32(action), jax.random.key(i))
        position, direction = tuple(int(v) for v in state.position), int(state.direction)
        assert (position, direction) == expected
        assert bool(ts.terminated) == (position == goal) and float(ts.reward) == float(position == goal)
        if ts.terminated:
            break
    assert blocked > 0  # walked into walls at least once


def test_reset_samples_start_different_from_goal(maze01):
    states, ts = jax.jit(jax.vmap(lambda k: maze01.reset(key=k)))(jax.random.split(jax.random.key(0), 20_000))
    free = {tuple(p) for p in np.asarray(maze01.free).tolist()}
    starts = [tuple(p) for p in np.asarray(states.position).tolist()]
    goals = [tuple(p) for p in np.asarray(states.goal).tolist()]
    assert all(s != g for s, g in zip(starts, goals))
    assert set(starts) == free and set(goals) == free  # uniform: 20k draws hit every one of the 109 cells
    counts = np.array(list(collections.Counter(starts).values()))
    assert counts.max() < 2 * counts.mean()
    assert set(np.asarray(states.direction).tolist()) == {0, 1, 2, 3}
    assert not ts.terminated.any() and ts.obs.shape == (20_000, 2, 3, 2)


def test_goal_is_terminal_and_next_episode_starts_immediately():
    env = E.make("Navix-DMLab-Maze-01-v0")
    bare = env.unwrapped
    state, _ = env.reset(key=jax.random.key(0))
    state = eqx.tree_at(lambda s: (s.env_state, s.t), state, (place((9, 10), EAST, (9, 11)), jnp.int32(5)))
    step = jax.jit(lambda s, a, k: env.step(s, a, key=k))
    state, ts = step(state, jnp.int32(FORWARD), jax.random.key(1))
    assert float(ts.reward) == 1.0 and bool(ts.terminated) and not bool(ts.truncated)
    np.testing.assert_array_equal(ts.final_obs, bare.observe(place((9, 11), EAST, (9, 11))))
    assert int(state.t) == 0  # a fresh episode, already begun
    np.testing.assert_array_equal(ts.obs, bare.observe(state.env_state))
    assert not np.array_equal(state.env_state.position, state.env_state.goal)
    state, ts = step(state, jnp.int32(LEFT), jax.random.key(2))
    assert int(state.t) == 1 and float(ts.reward) == 0.0 and not bool(ts.done)


def test_truncation_at_the_time_limit():
    env = E.make("Navix-DMLab-Maze-01-v0")
    assert env.max_steps_in_episode == MAX_STEPS["01"] == 2000

    def run(key):
        state, _ = env.reset(key=key)

        def body(state, k):
            state, ts = env.step(state, jnp.int32(LEFT), key=k)  # spinning never reaches the goal
            return state, (ts.truncated, ts.terminated)

        return jax.lax.scan(body, state, jax.random.split(key, 2001))[1]

    truncated, terminated = jax.jit(run)(jax.random.key(0))
    assert not terminated.any()
    assert np.flatnonzero(np.asarray(truncated)).tolist() == [1999]


def test_oracle_is_optimal_on_a_tiny_maze():
    walls = parse_layout(TINY)
    free = [tuple(p) for p in np.argwhere(~walls).tolist()]
    dist = shortest_distances(walls)

    def bfs(start, direction, goal):  # forward search over (cell, direction) from one start
        seen, queue = {(start, direction)}, collections.deque([(start, direction, 0)])
        while queue:
            position, d, n = queue.popleft()
            if position == goal:
                return n
            for action in (LEFT, RIGHT, FORWARD):
                nxt = reference_step(walls, position, d, action)
                if nxt not in seen:
                    seen.add(nxt)
                    queue.append((*nxt, n + 1))

    triples = [(s, d, g) for g in free for s in free for d in range(4) if s != g]
    expected = np.array([bfs(s, d, g) for s, d, g in triples])
    got = np.array([dist[free.index(g), free.index(s), d] for s, d, g in triples])
    np.testing.assert_array_equal(got, expected)
    value = oracle_values(walls, 0.99)
    assert value["optimal_discounted_return"] == pytest.approx(np.mean(0.99 ** (expected - 1.0)))
    assert value["optimal_mean_episode_length"] == pytest.approx(expected.mean())

    # The oracle policy, run in the environment from every triple, reaches the goal in exactly that many steps.
    env, oracle = DMLabMaze(layout=TINY), MazeOracle(walls)
    start = place_many([t[0] for t in triples], [t[1] for t in triples], [t[2] for t in triples])

    def episode_length(state):
        def body(carry, k):
            state, length, done = carry
            state, ts = env.step(state, oracle(state.position, state.direction, state.goal), key=k)
            return (state, length + (~done).astype(jnp.int32), done | ts.terminated), None

        return jax.lax.scan(body, (state, jnp.int32(0), jnp.asarray(False)), jax.random.split(jax.random.key(0), 12))[0]

    _, lengths, done = jax.jit(jax.vmap(episode_length))(start)
    assert done.all()
    np.testing.assert_array_equal(lengths, expected)


def test_oracle_values_of_the_mazes():
    for maze_id, value, length in [("01", 0.771, 28.4), ("02", 0.659, 45.7), ("03", 0.520, 75.4)]:
        exact = oracle_values(parse_layout(load_layouts()[maze_id]), 0.99)
        assert exact == pytest.approx(ORACLE_VALUES[maze_id], rel=1e-12)
        assert round(exact["optimal_discounted_return"], 3) == value
        assert round(exact["optimal_mean_episode_length"], 1) == length
        assert E.spec(f"Navix-DMLab-Maze-{maze_id}-v0").reference() == {**ORACLE_VALUES[maze_id],
                                                                         **RANDOM_POLICY_VALUES[maze_id]}


def random_policy(name: str, num_envs: int, steps: int, seed: int = 0) -> dict:
    """Mean undiscounted and discounted return of the uniformly random policy over the episodes that ended (as the
    training logs average): `num_envs` copies of the registered environment (time limit, auto-reset) for `steps`
    steps each. The registry's `RANDOM_POLICY_VALUES` are `random_policy(maze, num_envs=256, steps=12000)`."""
    env = E.make(name, "partial")

    def run(key):
        k_reset, k_run = jax.random.split(key)
        state, _ = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_reset, num_envs))
        zeros = jnp.zeros(num_envs)

        def step(carry, k):
            state, ret, disc, discount, sums = carry
            k_act, k_env = jax.random.split(k)
            action = jax.vmap(env.action_space.sample)(jax.random.split(k_act, num_envs))
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, action, jax.random.split(k_env, num_envs))
            ret, disc, done = ret + ts.reward, disc + discount * ts.reward, ts.done
            sums = (sums[0] + done, sums[1] + jnp.where(done, ret, 0.0), sums[2] + jnp.where(done, disc, 0.0))
            return (state, ret * ~done, disc * ~done, jnp.where(done, 1.0, discount * env.gamma), sums), None

        carry = (state, zeros, zeros, jnp.ones(num_envs), (zeros, zeros, zeros))
        return jax.lax.scan(step, carry, jax.random.split(k_run, steps))[0][-1]

    episodes, ret, disc = (float(np.asarray(x).sum()) for x in jax.jit(run)(jax.random.key(seed)))
    return {"episodes": episodes, "return": ret / episodes, "disc_return": disc / episodes}


@pytest.mark.parametrize("maze_id", [pytest.param("01", marks=pytest.mark.slow), pytest.param("02", marks=pytest.mark.slow),
                                     pytest.param("03", marks=pytest.mark.slow)])
def test_random_policy_values_are_what_a_random_policy_gets(maze_id):
    """The command that made the registry's constants: the same seed and size give them to their printed digits."""
    measured = random_policy(f"Navix-DMLab-Maze-{maze_id}-v0", num_envs=256, steps=12000, seed=0)
    stored = RANDOM_POLICY_VALUES[maze_id]
    assert measured["episodes"] > 256  # more than one finished episode per environment on average
    assert measured["disc_return"] == pytest.approx(stored["random_policy_discounted_return"], abs=6e-4)
    assert measured["return"] == pytest.approx(stored["random_policy_undiscounted_return"], abs=6e-3)


def test_jit_vmap_and_determinism():
    env = E.make("Navix-DMLab-Maze-02-v0")

    def rollout(key):
        state, ts = env.reset(key=key)

        def body(state, k):
            state, ts = env.step(state, jax.random.randint(k, (), 0, 3), key=k)
            return state, (ts.obs, ts.reward)

        return jax.lax.scan(body, state, jax.random.split(key, 50))[1]

    keys = jax.random.split(jax.random.key(7), 4)
    batched_fn = jax.jit(jax.vmap(rollout))
    batched, again = batched_fn(keys), batched_fn(keys)
    single = jax.jit(rollout)(keys[2])  # unbatched
    for a, b, c in zip(batched, again, single):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a[2], c)
    assert not np.array_equal(batched[0][0], batched[0][1])  # different keys, different episodes


def test_full_observation_is_centred_on_the_agent():
    env = DMLabMaze("03", "full")
    h, w = env.height, env.width
    assert env.observation_space.shape == (2 * h - 1, 2 * w - 1, 6) == (53, 81, 6)
    walls = np.asarray(env.walls)
    states, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(jax.random.key(0), 8))
    for i in range(8):
        obs = np.asarray(ts.obs[i])
        (r, c), (gr, gc), d = np.asarray(states.position[i]), np.asarray(states.goal[i]), int(states.direction[i])
        expected = np.ones((2 * h - 1, 2 * w - 1), np.float32)  # outside the maze counts as wall
        expected[h - 1 - r : 2 * h - 1 - r, w - 1 - c : 2 * w - 1 - c] = walls
        np.testing.assert_array_equal(obs[..., 0], expected)
        assert obs[h - 1, w - 1, 0] == 0.0  # the agent's own cell
        assert obs[..., 1].sum() == 1.0 and obs[h - 1 + gr - r, w - 1 + gc - c, 1] == 1.0
        np.testing.assert_array_equal(obs[..., 2:], np.broadcast_to(np.eye(4)[d], (2 * h - 1, 2 * w - 1, 4)))


@pytest.mark.slow
def test_perfect_memory_is_the_view_and_the_pose_and_goal_one_hot():
    """`perfect_memory` = the first-person view flattened, then one-hots of the agent's row, column and direction and of
    the goal's row and column: the state itself, read back exactly, over resets and steps."""
    env, partial = DMLabMaze("02", "perfect_memory"), DMLabMaze("02", "partial")
    h, w = env.height, env.width
    assert env.observation_space.shape == (12 + 2 * h + 2 * w + 4,) == (116,)
    states, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(jax.random.key(0), 16))
    step = jax.vmap(lambda s, a, k: env.step(s, a, key=k))
    states, ts = step(states, jnp.full(16, 2), jax.random.split(jax.random.key(1), 16))
    for i in range(16):
        obs, state = np.asarray(ts.obs[i]), jax.tree.map(lambda x: x[i], states)
        assert obs.dtype == bool and bool(env.observation_space.contains(ts.obs[i]))
        np.testing.assert_array_equal(obs[:12], np.asarray(partial.observe(state)).reshape(-1))
        row, col, d, goal_row, goal_col = np.split(obs[12:], np.cumsum([h, w, 4, h]))
        assert all(part.sum() == 1 for part in (row, col, d, goal_row, goal_col))
        (r, c), (gr, gc) = np.asarray(state.position), np.asarray(state.goal)
        decoded = (row.argmax(), col.argmax(), d.argmax(), goal_row.argmax(), goal_col.argmax())
        assert decoded == (r, c, int(state.direction), gr, gc)


@pytest.mark.slow
def test_egocentric_encoder_sees_the_partial_view_ahead():
    """The `egocentric` encoder of the full view puts the 2x3 cells ahead of the agent where the first-person view
    has them: rows -2 and -1, columns -1..1 around the centre of the turned map."""
    from pobax.agent import make_encoder

    for maze_id in ("01", "02"):
        full, partial = DMLabMaze(maze_id, "full"), DMLabMaze(maze_id, "partial")
        enc = make_encoder(full.observation_space.shape, 8, key=jax.random.key(0), kind="egocentric")
        side = max(full.observation_space.shape[:2])
        states, _ = jax.vmap(lambda k: full.reset(key=k))(jax.random.split(jax.random.key(1), 64))
        turned = jax.vmap(lambda s: enc(full.observe(s)))(states).reshape(64, side, side, 2)
        views = jax.vmap(partial.observe)(states)
        c = side // 2
        np.testing.assert_array_equal(np.asarray(turned[:, c - 2 : c, c - 1 : c + 2]), np.asarray(views, np.float32))
        assert set(np.asarray(states.direction).tolist()) == {0, 1, 2, 3}


def test_registry_metadata_and_wrappers():
    for maze_id in ("01", "02", "03"):
        name = f"Navix-DMLab-Maze-{maze_id}-v0"
        env = E.make(name)
        assert env.unwrapped.maze_id == maze_id and env.max_steps_in_episode == MAX_STEPS[maze_id]
        assert env.action_space.n == 3 and env.gamma == 0.99
        s = E.spec(name)
        assert s.observabilities == ("partial", "perfect_memory", "full")
        assert s.ceiling_observability == "perfect_memory"  # the paper's `full` map is asked for by name
        assert s.categories == ("spatial uncertainty", "episode nonstationarity")
    assert E.spec("Navix-DMLab-Maze-01-v0").recommended["num_envs"] == 256
    assert E.spec("Navix-DMLab-Maze-02-v0").best["ld"]["lambda1"] == 0.95
    with pytest.raises(E.UnknownEnvironmentError, match="Navix-DMLab-Maze-01-v0"):
        E.make("Navix-DMLab-Maze-04-v0")
    with pytest.raises(ValueError, match="partial, perfect_memory, full"):
        E.make("Navix-DMLab-Maze-01-v0", "belief")
    concat = E.make("Navix-DMLab-Maze-01-v0", action_concat=True)
    _, ts = concat.reset(key=jax.random.key(0))
    assert concat.observation_space.shape == ts.obs.shape == (2, 3, 5)
    assert bool(concat.observation_space.contains(ts.obs))
