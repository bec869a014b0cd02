"""`render_episode`: one episode of a trained agent as an animated GIF and a PNG strip of frames.

Each frame shows the environment (drawn per family, `_render.py`), beside it the memory's state over the episode
as a heat map (units × steps, filled up to the current step; where the agent has a memory), and a caption with
the step, the action taken from this state, the reward so far and the critic's value.
"""

import dataclasses
import io
import os
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from ._args import as_path, check_bools
from ._episodes import Episode, episode_env, record_episode
from ._files import atomic_write_bytes, check_figure_path, check_output_dir
from ._load import LoadedRun, load_run
from ._render import BG, HEIGHT, drawer_for, font

MEMORY_WIDTH = 220  # pixels of the memory panel
MAX_UNITS = 64  # memory units shown: the most active ones when there are more
CAPTION = 34


class RenderError(ValueError):
    """A render that cannot be made as asked: an output that cannot be written (a name that is neither .gif nor
    .png), or an argument of the wrong kind (greedy "no", fps 0)."""


#: The frame rates a GIF can hold (`save_gif`): its frames' durations in ms, 10 ms (GIF's unit) to 10 s.
FPS_RANGE = (0.1, 100.0)


def check_fps(fps, where: str = "render_episode") -> None:
    """A RenderError unless `fps` is a number of frames a second in `FPS_RANGE` (checked before an episode plays:
    0, nan or a string failed only when the GIF was written, at the end)."""
    lo, hi = FPS_RANGE
    ok = isinstance(fps, (int, float, np.integer, np.floating)) and not isinstance(fps, (bool, np.bool_))
    if not (ok and lo <= fps <= hi):  # (nan is in no range)
        raise RenderError(f"{where}: fps must be a number from {lo:g} to {hi:g} (frames a second of the GIF), "
                          f"got {fps!r}.")


@dataclasses.dataclass
class RenderResult:
    """What `render_episode` wrote (`gif`, `png`: the strip), the frames (RGB arrays) and the episode."""

    gif: Path | None
    png: Path | None
    frames: list[np.ndarray]
    episode: Episode


def _colormap(values: np.ndarray) -> np.ndarray:
    """Values in [-1, 1] as RGB: blue for negative, white at zero, red for positive."""
    import matplotlib

    return (matplotlib.colormaps["RdBu_r"]((np.clip(values, -1, 1) + 1) / 2)[..., :3] * 255).astype(np.uint8)


def memory_panel(memory: np.ndarray, t: int, height: int, width: int = MEMORY_WIDTH, label: str = "memory") -> np.ndarray:
    """The memory's state (steps × units) as a heat map of `height` × `width` pixels: a column per step up to step `t`
    (later steps blank), a row per unit (the `MAX_UNITS` that vary most over the episode when there are more)."""
    steps, units = memory.shape
    order = np.arange(units)
    if units > MAX_UNITS:
        order = np.sort(np.argsort(-memory.std(axis=0))[:MAX_UNITS])
    m = memory[:, order].T  # (units, steps)
    scale = max(float(np.abs(m).max()), 1e-6)
    colours = _colormap(m / scale)
    colours[:, t + 1:] = 235  # not yet
    top, left = 16, 4
    h, w = height - top - 4, width - 2 * left
    img = Image.fromarray(colours).resize((w, h), Image.NEAREST)
    panel = Image.new("RGB", (width, height), BG)
    panel.paste(img, (left, top))
    d = ImageDraw.Draw(panel)
    d.text((left, 1), f"{label}: {len(order)} units x {steps} steps", fill=(0, 0, 0), font=font(10))
    if t < steps:
        x0, x1 = left + w * t / steps, left + w * (t + 1) / steps
        d.rectangle((x0, top - 1, max(x1, x0 + 1), top + h), outline=(0, 0, 0))
    return np.asarray(panel)


def _pad_to(img: np.ndarray, height: int, width: int) -> np.ndarray:
    out = np.full((height, width, 3), 255, np.uint8)
    out[: img.shape[0], : img.shape[1]] = img[:height, :width]
    return out


def compose(pictures: list[np.ndarray], episode: Episode, captions: list[str], memory_label: str) -> list[np.ndarray]:
    """Frames of equal size: each picture, the memory panel beside it (if there is a memory), a caption below."""
    height = max(max(p.shape[0] for p in pictures), HEIGHT)
    width = max(p.shape[1] for p in pictures)
    frames = []
    for t, (pic, text) in enumerate(zip(pictures, captions)):
        parts = [_pad_to(pic, height, width)]
        if episode.memory is not None:
            parts.append(np.full((height, 6, 3), 255, np.uint8))
            parts.append(memory_panel(episode.memory, t, height, label=memory_label))
        body = np.concatenate(parts, axis=1)
        img = Image.new("RGB", (body.shape[1], body.shape[0] + CAPTION), BG)
        img.paste(Image.fromarray(body), (0, 0))
        ImageDraw.Draw(img).multiline_text((4, body.shape[0] + 2), text, fill=(0, 0, 0), font=font(11), spacing=2)
        frames.append(np.asarray(img))
    return frames


def _captions(env, episode: Episode, name) -> list[str]:
    gamma = episode.gamma
    ret, disc, out = 0.0, 0.0, []
    for t in range(episode.length + 1):
        if t < episode.length:
            what = f"step {t}: {name(env, episode.actions[t])}"
            value = f"value {float(episode.values[t][0]):.2f}"
        else:
            what = "terminated" if episode.terminated else "time limit" if episode.truncated else "cut"
            what, value = f"step {t}: end ({what})", ""
        out.append(f"{what}\nreturn {ret:.2f} (discounted {disc:.2f})  {value}")
        if t < episode.length:
            ret += float(episode.rewards[t])
            disc += float(episode.rewards[t]) * gamma**t
    return out


def save_gif(frames: list[np.ndarray], path: str | os.PathLike, fps: float | int = 4.0) -> Path:
    """Write RGB frames as an animated GIF that loops, `fps` frames a second (`FPS_RANGE`)."""
    check_fps(fps, "save_gif")
    path = Path(path)
    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()  # written whole (`atomic_write_bytes`): never half a GIF to a reader, nor through a link
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0,
                   disposal=1)
    atomic_write_bytes(path, buf.getvalue())
    return path


def save_strip(frames: list[np.ndarray], path: str | os.PathLike, count: int = 12, cols: int = 4) -> Path:
    """Write up to `count` frames, evenly spaced over the episode (its first and last included), as one PNG grid."""
    from ..env import save_frame_grid

    pick = np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))
    with tempfile.TemporaryDirectory() as scratch:  # drawn aside, then written whole, as `save_gif`
        grid = os.path.join(scratch, "strip.png")
        save_frame_grid(np.stack([frames[i] for i in pick]), grid, cols=cols, scale=1, gap=6)
        atomic_write_bytes(Path(path), Path(grid).read_bytes())
    return Path(path)


def _outputs(out: Path | None) -> tuple[Path | None, Path | None]:
    if out is None:
        return None, None
    if out.suffix.lower() not in (".gif", ".png"):
        raise RenderError(f"--out {str(out)!r}: name a .gif (the animation; the strip goes beside it as .png) or a "
                          f".png (the strip only).")
    check_figure_path(out)
    if out.suffix.lower() == ".png":
        return None, out
    strip = out.with_suffix(".png")
    if os.path.lexists(strip) and not os.path.lexists(out):  # not the strip of an earlier `render` to this .gif
        raise RenderError(f"--out {str(out)!r} writes its strip to {str(strip)!r}, which exists and is not the strip "
                          f"of an earlier render to this .gif: name another .gif, or move {str(strip)!r} aside.")
    check_figure_path(strip, "--out's strip")
    return out, strip


def render_episode(
    run: LoadedRun | str | os.PathLike,
    out: str | os.PathLike | None = "episode.gif",
    *,
    set: int | None = None,  # noqa: A002  (the CLI's word)
    seed_index: int = 0,
    index: int | None = None,
    seed: int = 0,
    greedy: bool = False,
    observability: str | None = None,
    max_steps: int = 200,
    fps: float | int = 4.0,
) -> RenderResult:
    """Play one episode with one trained run and draw it: the environment as a picture per step (T-Maze's corridor
    and cue, RockSample's board and checks, Battleship's hits and misses, the maze and the agent's view, pixel
    frames, masked MuJoCo's joint trajectories), the memory's state as a heat map beside it, a caption with the
    action, the return so far and the value. `out` `x.gif` writes the animation and `x.png` (a strip of up to 12
    frames); `x.png` the strip only; None nothing. The run is picked by `index`, else by hyperparameter `set`
    (default: the best by AUC) and `seed_index`; the episode is episode 0 of `evaluate` with the same `seed`, cut
    after `max_steps` steps; `fps`, the GIF's frames a second (`FPS_RANGE`). Paths may start with `~`. Arguments of
    the wrong kind are refused (RenderError) before the episode plays."""
    check_bools("render_episode", RenderError, greedy=greedy)
    check_fps(fps)
    out = as_path("render_episode", "out", out, RenderError, none=True, what="a file path")
    gif, png = _outputs(out)
    if out is not None:
        check_output_dir(out.parent, "render writes its .gif and .png", RenderError, named=out)
    run = load_run(run) if not isinstance(run, LoadedRun) else run
    drawer = drawer_for(run.env)
    i = run.index(set, seed_index) if index is None else index
    env = episode_env(run, observability)
    episode = record_episode(run, drawer.capture, env=env, index=i, seed=seed, greedy=greedy, max_steps=max_steps)
    pictures = drawer.draw(env.unwrapped, episode.views, episode.actions)
    label = f"memory ({run.config.memory})"
    frames = compose(pictures, episode, _captions(env.unwrapped, episode, drawer.action_name), label)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
    if gif is not None:
        save_gif(frames, gif, fps)
    if png is not None:
        save_strip(frames, png)
    return RenderResult(gif, png, frames, episode)
