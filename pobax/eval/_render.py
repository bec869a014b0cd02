"""Pictures of environment states, per family: what `render_episode` draws beside the agent's memory.

Each family has a `Drawer`: `capture(env, state, obs)` (traced, inside the episode's program) keeps the little a
picture needs of a raw environment state (and of the observation the agent saw); `draw(env, views, actions)`
(on the host, NumPy and Pillow) turns the T + 1 captured views of an episode into T + 1 RGB frames, frame t showing
the state before action t and the last frame the final state; `action_name(env, a)` labels an action.

Grid worlds are drawn as pictures (T-Maze, RockSample, Battleship, the DMLab mazes), pixel environments from
their frames (pixel MuJoCo, Craftax), masked MuJoCo as a plot of its joint trajectories (no MuJoCo renderer is
needed), and any other environment from its observation.
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ..env import Battleship, BraxEnv, DMLabMaze, PixelBrax, RockSample, TMaze, observation_array
from ..env._base import check_seed, random_rollout

BG, GRID, AGENT = (255, 255, 255), (170, 170, 170), (40, 90, 220)
GOOD, BAD, CUE, HIGHLIGHT = (60, 170, 80), (215, 70, 60), (245, 170, 30), (255, 220, 60)
HEIGHT = 200  # pixels of the environment's picture (frames of pixel environments are scaled up to about this)


class Drawer(NamedTuple):
    """How to capture and draw the states of one environment family (see the module docstring)."""

    capture: Callable
    draw: Callable
    action_name: Callable


def font(size: int = 12) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """Pillow's bundled font at `size` pixels."""
    return ImageFont.load_default(size=size)


def _canvas(width: int, height: int) -> tuple[Image.Image, ImageDraw.ImageDraw]:
    img = Image.new("RGB", (int(width), int(height)), BG)
    return img, ImageDraw.Draw(img)


def _cell(c, row, col, pad=0, margin=0) -> tuple[int, int, int, int]:
    """The pixel box (x0, y0, x1, y1) of grid cell (row, col) with cells of c pixels, inset by `pad`."""
    c, row, col = int(c), int(row), int(col)
    return (margin + col * c + pad, margin + row * c + pad, margin + (col + 1) * c - pad - 1, margin + (row + 1) * c - pad - 1)


def _scaled(image: np.ndarray, height: int = HEIGHT) -> np.ndarray:
    """An RGB image scaled by a whole factor (nearest neighbour) to about `height` rows."""
    k = max(1, height // image.shape[0])
    return image.repeat(k, axis=0).repeat(k, axis=1)


def _rgb(x) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype != np.uint8:
        x = np.clip(np.round(x * (255.0 if x.max(initial=0) <= 1.0 else 1.0)), 0, 255).astype(np.uint8)
    return x[..., :3]


def _frames(views, count: int, one) -> list[np.ndarray]:
    return [np.asarray(one({k: np.asarray(v)[t] for k, v in views.items()}, t)) for t in range(count)]


def _n(views) -> int:
    return len(next(iter(views.values())))


def _state_view(names: tuple[str, ...]):
    """A capture that keeps the named fields of the raw state."""
    return lambda env, state, obs: {k: getattr(state, k) for k in names}


# --- T-Maze: the corridor, the cue at the start, the goal arm, the agent ---------------------------------------

def _tmaze_draw(env: TMaze, views, actions) -> list[np.ndarray]:
    n = env.length + 2
    c = int(np.clip(360 // n, 14, 40))
    m = 6

    def one(v, t):
        img, d = _canvas(n * c + 2 * m, 3 * c + 2 * m)
        up = bool(v["goal_up"])
        for col in range(n):
            d.rectangle(_cell(c, 1, col, margin=m), fill=(235, 235, 235), outline=GRID)
        for row, is_goal in ((0, up), (2, not up)):
            d.rectangle(_cell(c, row, n - 1, margin=m), fill=GOOD if is_goal else BAD, outline=GRID)
        x0, y0, x1, y1 = _cell(c, 1, 0, pad=c // 10, margin=m)  # the cue: a triangle pointing to the goal's side
        tip, base = (y0, y1) if up else (y1, y0)
        d.polygon([((x0 + x1) / 2, tip), (x0, base), (x1, base)], fill=CUE)
        row = 1
        if t == len(actions) and t > 0 and int(v["pos"]) == n - 1 and int(actions[-1]) in (0, 2):
            row = 0 if int(actions[-1]) == 0 else 2  # the final turn into an arm
        d.ellipse(_cell(c, row, int(v["pos"]), pad=c // 3, margin=m), fill=AGENT, outline=BG)
        d.text((m, m), f"cue: {'up' if up else 'down'}", fill=(0, 0, 0), font=font(11))
        return img

    return _frames(views, _n(views), one)


# --- RockSample: the grid, the rocks (true goodness, the agent's last reading), checks, the exit ------------------

def _rocksample_draw(env: RockSample, views, actions) -> list[np.ndarray]:
    n = env.size
    c = int(np.clip(HEIGHT // n, 12, 40))
    m = 4
    rocks = np.asarray(env.rock_positions)

    def one(v, t):
        img, d = _canvas((n + 1) * c + 2 * m, n * c + 2 * m)
        for r in range(n):
            for q in range(n):
                d.rectangle(_cell(c, r, q, margin=m), outline=GRID)
            d.rectangle(_cell(c, r, n, margin=m), fill=(200, 235, 200))
        d.text((m + n * c + 2, m + 2), "exit", fill=(0, 90, 0), font=font(10))
        reading = np.asarray(v["rock_obs"])
        for i, (r, q) in enumerate(rocks):
            ring = {1.0: GOOD, -1.0: BAD}.get(float(reading[i]), GRID)
            d.ellipse(_cell(c, r, q, pad=c // 8, margin=m), fill=ring)
            d.ellipse(_cell(c, r, q, pad=c // 4, margin=m), fill=GOOD if v["rock_good"][i] else BAD)
            if c >= 16:
                d.text(_cell(c, r, q, margin=m)[:2], str(i), fill=(0, 0, 0), font=font(9))
        pr, pq = (int(x) for x in v["pos"])
        checked = int(v["observed"])
        if t > 0 and checked >= 0 and int(actions[t - 1]) >= 5:  # the check just made: a line to the rock
            cr, cq = rocks[checked]
            d.line([(m + (pq + .5) * c, m + (pr + .5) * c), (m + (cq + .5) * c, m + (cr + .5) * c)], fill=CUE, width=3)
        d.rectangle(_cell(c, pr, pq, pad=c // 3, margin=m), fill=AGENT)
        return img

    return _frames(views, _n(views), one)


def _rocksample_action(env: RockSample, a) -> str:
    a = int(a)
    return ("north", "east", "south", "west", "sample")[a] if a < 5 else f"check rock {a - 5}"


# --- Battleship: hits and misses over the (faintly drawn) ships, the last shot ----------------------------------

def _battleship_draw(env: Battleship, views, actions) -> list[np.ndarray]:
    n = env.size
    c = int(np.clip(HEIGHT // n, 10, 40))
    m = 4

    def one(v, t):
        img, d = _canvas(n * c + 2 * m, n * c + 2 * m)
        ships, fired = np.asarray(v["ships"]), np.asarray(v["fired"])
        for cell in range(n * n):
            r, q = divmod(cell, n)
            box = _cell(c, r, q, margin=m)
            d.rectangle(box, fill=(205, 205, 215) if ships[cell] >= 0 else (225, 238, 250), outline=GRID)
            if fired[cell] and ships[cell] >= 0:  # a hit: a red cross
                d.rectangle(_cell(c, r, q, pad=1, margin=m), fill=BAD)
                d.line([box[:2], box[2:]], fill=BG, width=2)
                d.line([(box[0], box[3]), (box[2], box[1])], fill=BG, width=2)
            elif fired[cell]:  # a miss: a dark dot
                d.ellipse(_cell(c, r, q, pad=c // 3, margin=m), fill=(30, 60, 120))
        last = int(v["last_action"])
        if last >= 0:
            d.rectangle(_cell(c, *divmod(last, n), margin=m), outline=HIGHLIGHT, width=3)
        return img

    return _frames(views, _n(views), one)


def _battleship_action(env: Battleship, a) -> str:
    r, q = divmod(int(a), env.size)
    return f"fire row {r} col {q}"


# --- DMLab maze: walls, the goal, the agent facing its direction, the cells it sees ------------------------------

def _maze_draw(env: DMLabMaze, views, actions) -> list[np.ndarray]:
    from ..env._dmlab_maze import _VIEW_OFFSETS

    walls = np.asarray(env.walls)
    h, w = walls.shape
    c = int(np.clip(2 * HEIGHT // max(h, w), 5, 24))
    m = 2

    def one(v, t):
        img, d = _canvas(w * c + 2 * m, h * c + 2 * m)
        for r, q in zip(*np.nonzero(walls)):
            d.rectangle(_cell(c, r, q, margin=m), fill=(60, 60, 60))
        gr, gq = (int(x) for x in v["goal"])
        d.rectangle(_cell(c, gr, gq, margin=m), fill=GOOD)
        pos, facing = np.asarray(v["position"]), int(v["direction"])
        if env.observability in ("partial", "perfect_memory"):  # the cells it sees
            for r, q in (pos[None, None, :] + _VIEW_OFFSETS[facing]).reshape(-1, 2):
                if 0 <= r < h and 0 <= q < w:
                    d.rectangle(_cell(c, r, q, margin=m), outline=CUE, width=max(1, c // 6))
        x0, y0, x1, y1 = _cell(c, int(pos[0]), int(pos[1]), pad=max(0, c // 8), margin=m)
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        tips = {0: [(x1, cy), (x0, y0), (x0, y1)], 1: [(cx, y1), (x0, y0), (x1, y0)],
                2: [(x0, cy), (x1, y0), (x1, y1)], 3: [(cx, y0), (x0, y1), (x1, y1)]}
        d.polygon(tips[facing], fill=AGENT)
        return img

    return _frames(views, _n(views), one)


# --- masked MuJoCo: the joint trajectories, a cursor at the current step ----------------------------------------

def _brax_capture(env: BraxEnv, state, obs):
    return {"pos": state.inner.obs[: env.spec.num_pos], "x": state.inner.pipeline_state.q[0]}


def _brax_draw(env: BraxEnv, views, actions) -> list[np.ndarray]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pos, x = np.asarray(views["pos"]), np.asarray(views["x"])
    steps = np.arange(len(x))
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(5.0, 3.2), dpi=80, sharex=True, height_ratios=(3, 1))
    for j, name in enumerate(env.spec.pos_names):
        ax.plot(steps, pos[:, j], lw=1, label=name)
    sees = {"P": "positions", "V": "velocities", "F": "everything"}[env.mask if env.observability == "partial" else "F"]
    ax.set_title(f"{env.robot}: joint positions (the agent sees {sees})", fontsize=8)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    bx.plot(steps, x, color="black", lw=1)
    bx.set_ylabel("torso x", fontsize=7)
    bx.set_xlabel("step", fontsize=7)
    for a in (ax, bx):
        a.tick_params(labelsize=6)
    fig.tight_layout()
    fig.canvas.draw()
    base = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    cols = [int(round(ax.transData.transform((s, 0))[0])) for s in steps]
    top, bottom = base.shape[0] - int(ax.bbox.y1), base.shape[0] - int(bx.bbox.y0)  # rows of the two plots
    plt.close(fig)
    frames = []
    for t in steps:
        f = base.copy()
        right = min(cols[-1] + 1, f.shape[1])
        future = f[top:bottom, cols[t] + 1:right]
        f[top:bottom, cols[t] + 1:right] = (0.35 * future + 0.65 * 255).astype(np.uint8)  # the future, faded
        f[top:bottom, max(cols[t] - 1, 0):cols[t] + 1] = (220, 40, 40)
        frames.append(f)
    return frames


def _continuous_action(env, a) -> str:
    return f"|a| = {np.linalg.norm(np.asarray(a)):.2f}"


# --- pixel environments: their frames ---------------------------------------------------------------------------

def _pixels_capture(env, state, obs):
    if env.observability == "partial":
        return {"frame": observation_array(obs)[..., :3]}
    render = env.render if isinstance(env, PixelBrax) else env.render_full_pixels
    return {"frame": render(state)}


def _pixels_draw(env, views, actions) -> list[np.ndarray]:
    return [_scaled(_rgb(f)) for f in np.asarray(views["frame"])]


def _craftax_action(env, a) -> str:
    try:
        from craftax.craftax.constants import Action

        return Action(int(a)).name.lower()
    except (ImportError, ValueError):
        return f"action {int(a)}"


# --- anything else: the observation ---------------------------------------------------------------------------

def _obs_capture(env, state, obs):
    return {"obs": observation_array(obs).astype(jnp.float32)}


def _obs_draw(env, views, actions) -> list[np.ndarray]:
    obs = np.asarray(views["obs"])
    if obs.ndim == 4 and obs.shape[-1] >= 3:
        return [_scaled(_rgb(o)) for o in obs]
    flat = obs.reshape(len(obs), -1)
    scale = max(np.abs(flat).max(), 1e-6)
    width = max(1, 400 // flat.shape[1])
    frames = []
    for o in flat:
        strip = np.full((40, flat.shape[1] * width, 3), 255, np.uint8)
        g = (255 * (1 - np.abs(o) / scale)).astype(np.uint8).repeat(width)
        strip[:, :, 0] = np.where(o.repeat(width) < 0, g, 255)
        strip[:, :, 1] = g
        strip[:, :, 2] = np.where(o.repeat(width) > 0, g, 255)
        frames.append(strip)
    return frames


def _discrete_action(env, a) -> str:
    return f"action {int(np.asarray(a).reshape(-1)[0])}" if np.asarray(a).size == 1 else _continuous_action(env, a)


def drawer_for(env) -> Drawer:
    """The drawer of an environment (wrapped or not), by the family of its innermost environment."""
    raw = env.unwrapped
    if isinstance(raw, TMaze):
        return Drawer(_state_view(("pos", "goal_up")), _tmaze_draw,
                      lambda e, a: ("up", "right", "down", "left")[int(a)])
    if isinstance(raw, RockSample):
        return Drawer(_state_view(("pos", "rock_good", "rock_obs", "observed")), _rocksample_draw, _rocksample_action)
    if isinstance(raw, Battleship):
        return Drawer(_state_view(("ships", "fired", "last_action")), _battleship_draw, _battleship_action)
    if isinstance(raw, DMLabMaze):
        return Drawer(_state_view(("position", "direction", "goal")), _maze_draw,
                      lambda e, a: ("turn left", "turn right", "forward")[int(a)])
    if isinstance(raw, PixelBrax):
        return Drawer(_pixels_capture, _pixels_draw, _continuous_action)
    if isinstance(raw, BraxEnv):
        return Drawer(_brax_capture, _brax_draw, _continuous_action)
    if type(raw).__name__ == "CraftaxNoInventory":  # imported lazily: Craftax is an extra
        return Drawer(_pixels_capture, _pixels_draw, _craftax_action)
    return Drawer(_obs_capture, _obs_draw, _discrete_action)


def random_frames(name: str, steps: int, seed: int = 0) -> list[np.ndarray]:
    """`steps` pictures of environment `name` under uniformly random actions, drawn as a trained agent's episode is
    (`drawer_for`): the state after reset, then one per action. For grid worlds (T-Maze, RockSample, Battleship, the
    DMLab mazes), whose observations are not pictures; `pobax render --env` draws the mazes with this."""
    from ..env import make  # noqa: PLC0415

    check_seed(seed)
    env = make(name, wrappers=False)
    drawer = drawer_for(env)
    run = jax.jit(lambda key: random_rollout(env, steps, key, lambda state, obs: drawer.capture(env, state, obs)))
    views, actions = jax.device_get(run(jax.random.key(seed)))
    return drawer.draw(env, views, actions)


def has_picture(name: str) -> bool:
    """Whether `pobax render --env` draws environment `name` with `random_frames`: the DMLab mazes, whose observations
    are grids of cell channels rather than pictures (other grid worlds are watched with a trained agent)."""
    from ..env import make  # noqa: PLC0415

    return isinstance(make(name, wrappers=False), DMLabMaze)
