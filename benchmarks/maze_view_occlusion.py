"""How much walls would hide of the DMLab mazes' partial view: pobax shows the 2 x 3 cells ahead unoccluded (the
paper's appendix gives the view's size, not whether walls hide cells behind them; docs/deviations.md).

Every pose (free cell x facing direction) of each maze is enumerated, exactly, and its view compared with the same
view under two occlusion rules:
- `line`: a cell two ahead is hidden when the cell in front of it (same column, one ahead) is a wall;
- `minigrid`: MiniGrid's `process_vis` on the 3 x 3 square of the view and the agent's row: visibility spreads from
  the agent up, sideways and diagonally up through cells that are not walls (a hidden cell reads as a wall).
For each maze and rule: the share of poses whose view changes, and the number of distinct wall views with and
without occlusion (fewer distinct views: more aliasing). Also the share of poses weighted by a uniformly random
policy's visits (`--walk-steps` steps of `--walkers` walkers from uniform poses, `--seed`). CPU only; prints a table,
`--json` writes it.

    python benchmarks/maze_view_occlusion.py --mazes 01 02 03 --json maze_view_occlusion.json
"""

import json
import platform

import jax
import numpy as np

from pobax._cli.args import ScriptParser
from pobax._version import commit
from pobax.env import DMLabMaze
from pobax.env._dmlab_maze import _VIEW_OFFSETS
from pobax.env._maze_oracle import DIRECTION_DELTAS

RULES = ("line", "minigrid")


def views(walls: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The unoccluded wall views (n, 2, 3) of `poses` (n, 3: row, column, direction), as pobax observes them."""
    cells = poses[:, None, None, :2] + _VIEW_OFFSETS[poses[:, 2]]
    h, w = walls.shape
    inside = (cells[..., 0] >= 0) & (cells[..., 0] < h) & (cells[..., 1] >= 0) & (cells[..., 1] < w)
    return ~inside | walls[np.clip(cells[..., 0], 0, h - 1), np.clip(cells[..., 1], 0, w - 1)]


def occlude(view: np.ndarray, rule: str) -> np.ndarray:
    """`view` (n, 2, 3: row 0 two ahead, row 1 one ahead; columns left, straight, right) with hidden cells as
    walls, under `rule`."""
    if rule == "line":
        out = view.copy()
        out[:, 0] |= view[:, 1]
        return out
    # MiniGrid's process_vis over rows (two ahead, one ahead, the agent's), the agent at the bottom centre; the
    # agent's row's side cells are not in pobax's view and are taken as open: they add nothing, since the agent's
    # own cell already shows the whole row one ahead.
    n = view.shape[0]
    grid = np.concatenate([view, np.zeros((n, 1, 3), bool)], axis=1)  # (n, 3, 3), walls
    mask = np.zeros((n, 3, 3), bool)
    mask[:, 2, 1] = True
    for j in (2, 1, 0):
        for order in (range(3), range(2, -1, -1)):
            for i in order:
                see = mask[:, j, i] & ~grid[:, j, i]
                step = 1 if order.step == 1 else -1
                if 0 <= i + step < 3:
                    mask[:, j, i + step] |= see
                    if j > 0:
                        mask[:, j - 1, i + step] |= see
                if j > 0:
                    mask[:, j - 1, i] |= see
    return view | ~mask[:, :2]


def random_walk_visits(walls: np.ndarray, free: np.ndarray, walkers: int, steps: int, seed: int) -> np.ndarray:
    """Visit counts (free cells x 4 directions) of a uniformly random policy (turn left, turn right, forward),
    walkers starting from uniform poses; goals are ignored (episodes do not end)."""
    rng = np.random.default_rng(seed)
    index = -np.ones(walls.shape, np.int64)
    index[free[:, 0], free[:, 1]] = np.arange(len(free))
    pos = free[rng.integers(0, len(free), walkers)]
    d = rng.integers(0, 4, walkers)
    counts = np.zeros((len(free), 4), np.int64)
    for _ in range(steps):
        np.add.at(counts, (index[pos[:, 0], pos[:, 1]], d), 1)
        a = rng.integers(0, 3, walkers)
        ahead = pos + DIRECTION_DELTAS[d]
        move = (a == 2) & ~walls[ahead[:, 0], ahead[:, 1]]
        pos = np.where(move[:, None], ahead, pos)
        d = np.where(a == 0, (d - 1) % 4, np.where(a == 1, (d + 1) % 4, d))
    return counts


def measure(maze_id: str, walkers: int, steps: int, seed: int) -> dict:
    env = DMLabMaze(maze_id)
    walls, free = np.asarray(env.walls), np.asarray(env.free)
    poses = np.array([(r, c, d) for r, c in free for d in range(4)], np.int64)
    plain = views(walls, poses)
    visits = random_walk_visits(walls, free, walkers, steps, seed).reshape(-1)
    row = {"maze": maze_id, "poses": len(poses), "distinct_views": len(np.unique(plain.reshape(len(poses), -1),
                                                                                   axis=0))}
    for rule in RULES:
        hidden = occlude(plain, rule)
        changed = (hidden != plain).any(axis=(1, 2))
        row[rule] = {"changed_poses": float(changed.mean()),
                     "changed_visits": float((changed * visits).sum() / visits.sum()),
                     "distinct_views": len(np.unique(hidden.reshape(len(poses), -1), axis=0))}
    return row


def main() -> None:
    p = ScriptParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mazes", nargs="+", default=["01", "02", "03"])
    p.add_argument("--walkers", type=int, default=256)
    p.add_argument("--walk-steps", type=int, default=4000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    print(f"CPU ({platform.processor() or platform.machine()}), JAX {jax.__version__}, pobax {commit()}")
    rows = [measure(m, args.walkers, args.walk_steps, args.seed) for m in args.mazes]
    print("maze  poses  distinct views  | rule      poses changed  visits changed  distinct views")
    for r in rows:
        for rule in RULES:
            x = r[rule]
            print(f"{r['maze']:>4}  {r['poses']:>5}  {r['distinct_views']:>14}  | {rule:<8}  "
                  f"{x['changed_poses']:>13.1%}  {x['changed_visits']:>14.1%}  {x['distinct_views']:>14}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": "python benchmarks/maze_view_occlusion.py " + " ".join(
                f"--{k.replace('_', '-')} {' '.join(v) if isinstance(v, list) else v}"
                for k, v in vars(args).items() if k != "json" and v is not None), "jax": jax.__version__,
                "pobax_commit": commit(), "device": "cpu",
                "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
