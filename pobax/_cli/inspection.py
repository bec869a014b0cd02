"""The commands that read runs or the registry: results, plot, eval, render and envs, and what they print."""

import sys
from pathlib import Path

from .._paths import printable
from .args import UsageError
from .commands import Envs, Eval, Plot, Render, Results


def run_results(cmd: Results) -> None:
    from pobax.eval import format_ci, list_runs

    if not cmd.root.is_dir():
        raise UsageError(f"--root {str(cmd.root)!r} is not a directory.")
    rows = list_runs(cmd.root)
    if not rows:
        print(f"no runs under {cmd.root}")
        return
    print(f"{'run directory':58s} {'env':24s} {'agent':16s} {'obs':14s} {'sets×seeds':>10s} {'state':>9s} {'final disc. return':>22s}")
    for r in rows:
        ret = (format_ci({"mean": r["disc_return"], "ci_low": r["ci_low"], "ci_high": r["ci_high"]})
               if r["disc_return"] is not None
               else "no episode ended" if r["state"] == "finished" else "")
        path, env, agent, obs = (printable(str(r[k])) for k in ("path", "env", "agent", "observability"))
        print(f"{path:58s} {env:24s} {agent:16s} {obs:14s} {r['sets']:>4d}×{r['seeds']:<5d} {r['state']:>9s} "
              f"{ret:>22s}")
    for r in rows:  # after the table, which stays one row per run: what is damaged and why
        if r.get("problem"):
            print(f"damaged: {printable(r['problem'])}", file=sys.stderr)


def _output_file(path: Path, flag: str = "--out") -> Path:
    """`path` as a file to write, its folder created; a one-line error if an existing parent is a file, the folder
    cannot be made, or `path` is an image's name holding a file that is not such an image (`check_figure_path`)."""
    from pobax.eval._files import check_figure_path
    from pobax.eval._results import writable_dir

    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise UsageError(f"{flag} {str(path)!r}: {str(parent)!r} is a file, not a directory.")
    if path.is_dir():
        raise UsageError(f"{flag} {str(path)!r} is a directory; pass a file name in it.")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        writable_dir(path.parent)
    except OSError as e:
        raise UsageError(f"{flag} {str(path)!r}: cannot write in {str(path.parent)!r} ({e.strerror or e}).") from None
    check_figure_path(path, flag)  # (an image's name holding another kind of file: not written over)
    return path


def run_plot(cmd: Plot) -> None:
    from pobax.eval import plot_runs

    if not cmd.runs:
        raise UsageError("plot needs at least one run directory.")
    if not cmd.out.is_dir() and not cmd.out.suffix:  # matplotlib would write OUT.png, and `plot` name OUT
        raise UsageError(f"--out {str(cmd.out)!r} is neither a directory nor an image name; pass e.g. "
                         f"{str(cmd.out.with_suffix('.png'))!r}, or an existing directory (curves.png inside).")
    if cmd.metric is not None and cmd.undiscounted:
        raise UsageError("--undiscounted chooses the return's curve and --metric another metric's: give one of them.")
    out = cmd.out / "curves.png" if cmd.out.is_dir() else cmd.out
    from matplotlib.backend_bases import FigureCanvasBase

    kinds = sorted(FigureCanvasBase.get_supported_filetypes())
    if out.suffix.lower().lstrip(".") not in kinds:
        raise UsageError(f"--out {str(out)!r}: matplotlib cannot write {out.suffix!r} figures; name one of "
                         f"{', '.join('.' + k for k in kinds)} (e.g. {str(out.with_suffix('.png'))!r}).")
    made = [p for p in {*out.parents, *(cmd.json.parents if cmd.json is not None else ())} if not p.exists()]
    try:
        out = _output_file(out)
        data = None if cmd.json is None else _output_file(cmd.json, "--json")
        column = cmd.metric or ("return" if cmd.undiscounted else "disc_return")
        path = plot_runs(cmd.runs, out, best=cmd.best, column=column, data=data)  # (refuses a --json not its own)
    except BaseException:  # refused (e.g. an unknown --metric): the folders made for its files go again
        for p in sorted(made, key=lambda q: len(q.parts), reverse=True):
            try:
                p.rmdir()
            except OSError:
                pass
        raise
    print(f"figure: {printable(path)}" + (f"\ncurves: {printable(data)}" if data is not None else ""))


def run_eval(cmd: Eval) -> None:
    from pobax.agent import config_from_dict
    from pobax.eval import RunDir, evaluate, format_eval
    from pobax.eval._bounds import check_eval_fits

    if (cmd.run / "config.json").is_file():  # (else evaluate says what is wrong with the path)
        record = RunDir(cmd.run).read_config()
        cfg = config_from_dict(record.get("config", {}), source=repr(str(cmd.run / "config.json")))
        check_eval_fits(cmd.episodes, cfg, len(cfg.grid()) * cfg.num_seeds)

    print(format_eval(evaluate(cmd.run, episodes=cmd.episodes, greedy=cmd.greedy, observability=cmd.observability,
                               seed=cmd.seed, max_steps=cmd.max_steps, out=cmd.out)))


RANDOM_FRAMES_MAX = 1024  # `render --env`: frames of one PNG grid


def run_render(cmd: Render) -> None:
    from pobax.env import make, render_frames, save_frame_grid

    if cmd.steps is not None and cmd.steps < 1:
        raise UsageError(f"--steps must be a positive integer, got {cmd.steps}.")
    if cmd.run is None and (cmd.steps or 0) > RANDOM_FRAMES_MAX:  # held in memory, then drawn as one picture
        raise UsageError(f"--steps {cmd.steps:,}: a grid of random frames holds at most {RANDOM_FRAMES_MAX:,}; to "
                         f"watch a longer episode, render a trained run (pobax render RUN_DIR --steps N).")
    if cmd.run is None and not 1 <= cmd.cols <= RANDOM_FRAMES_MAX:
        raise UsageError(f"--cols must be an integer in [1, {RANDOM_FRAMES_MAX:,}], got {cmd.cols:,}.")
    if cmd.run is not None:
        from pobax.eval import render_episode

        if cmd.env is not None:
            raise UsageError("render takes a run directory (a trained agent) or --env (random actions), not both.")
        out = cmd.out if cmd.out is not None else cmd.run / "episode.gif"  # its folder is made once the run loads
        r = render_episode(cmd.run, out, set=cmd.set, seed_index=cmd.run_seed, seed=cmd.seed, greedy=cmd.greedy,
                           observability=cmd.observability, max_steps=cmd.steps or 200)
        ret, disc = r.episode.returns
        print(f"{len(r.frames)} frames ({r.episode.length} steps, return {ret:.3f}, discounted {disc:.3f}) -> "
              + ", ".join(printable(p) for p in (r.gif, r.png) if p is not None))
        return
    env = cmd.env or "halfcheetah_pixels"
    if cmd.out is not None and cmd.out.suffix.lower() != ".png":
        raise UsageError(f"--out {str(cmd.out)!r}: random frames are drawn as one PNG grid; name a .png "
                         f"(e.g. {str(cmd.out.with_suffix('.png'))!r}).")
    from pobax.eval._render import has_picture, random_frames

    if has_picture(env):  # a maze: drawn as a trained agent's episode is
        import numpy as np

        out = _output_file(cmd.out or Path("frames.png"))
        frames = np.stack(random_frames(env, cmd.steps or 32, cmd.seed))
        save_frame_grid(frames, str(out), cols=cmd.cols, scale=1)
        print(f"{len(frames)} frames of {env} -> {printable(out)}")
        return
    shape = getattr(make(env, wrappers=False).observation_space, "shape", None)
    if shape is None or len(shape) != 3:
        raise UsageError(f"{env!r} has no image observation (shape {shape}); render one of the *_pixels "
                         f"environments, or a trained agent: pobax render RUN_DIR.")
    out = _output_file(cmd.out or Path("frames.png"))
    frames = render_frames(env, cmd.steps or 32, cmd.seed)
    save_frame_grid(frames, str(out), cols=cmd.cols)
    print(f"{len(frames)} frames of {env} -> {printable(out)}")


def run_envs(cmd: Envs) -> None:
    from pobax.env._registry import _FAMILIES

    for f in _FAMILIES:
        ids = ", ".join(f.registered)
        print(f"{f.template:32s} observabilities: {', '.join(f.observabilities):32s} paper IDs: {ids}")
        print(f"{'':32s} categories: {', '.join(f.categories)}")
