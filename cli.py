"""pobax command line: `python cli.py <command> --help` (also installed as `pobax`).

Commands:
  train    train PPO agents (every combination of list-valued hyperparameters × seeds in one compiled program)
  sweep    sweep a grid, select the best set by AUC, write it as a preset file (and re-run it with fresh seeds)
  gap      memory-improvability gap report: floor (memoryless, partial), memory agents, ceiling (full state)
  benchmark  the gap report's agents on a suite of environments at a named budget: one results table and figure
  results  list the runs under a directory
  plot     learning curves with 95% CIs from any set of run directories
  render   save a grid of frames of an image environment under random actions (e.g. halfcheetah_pixels)
  envs     list the registered environments
"""

import dataclasses
import sys
from pathlib import Path
from typing import Literal

import tyro

from pobax.agent import NUMERIC, TrainConfig
from pobax.eval._gap import AGENTS


@dataclasses.dataclass(frozen=True)
class Train(TrainConfig):
    """Train PPO agents on one environment; list values (e.g. `--lr 2.5e-3 2.5e-4`) are swept together."""

    out: Path | None = None
    """Run directory (default: runs/<env>-<observability>-<memory>-<time>). Must not already hold results."""
    quiet: bool = False
    """No progress output."""
    preset: str | None = None
    """`paper`: the environment's recommended settings and the paper's best hyperparameters for this agent; or
    a preset JSON file (e.g. `best.json` from `sweep`). Flags given explicitly override the preset."""
    resume: Path | None = None
    """Continue the interrupted run in this directory, with its saved configuration (other flags are ignored)."""
    max_chunks: int | None = None
    """Stop after this many chunks, leaving a run that `--resume` continues."""
    log: tuple[str, ...] = ()
    """Also log to these trackers when installed: tensorboard (into <run>/tensorboard), wandb."""


@dataclasses.dataclass(frozen=True)
class Sweep(Train):
    """Train a grid (list-valued hyperparameters × seeds in one program; `--axis` values as separate programs),
    select the set with the largest area under the discounted learning curve, and write it as `best.json`."""

    axis: tuple[str, ...] = ()
    """Structural axes, compiled one after another, e.g. `--axis hidden_size=64,128 num_envs=4,8`."""
    rerun_seeds: int = 0
    """Re-run the selected set with this many fresh seeds (the paper re-runs with 30) into <out>/rerun."""
    max_runs: int | None = None
    """Runs (sets × seeds) per compiled program; larger grids are split (default: from a device-memory estimate)."""


@dataclasses.dataclass(frozen=True)
class Results:
    """List the runs under a directory: environment, agent, seeds, state and final discounted return."""

    root: Path = Path("runs")
    """Directory to search (recursively) for run directories."""


@dataclasses.dataclass(frozen=True)
class Plot:
    """Learning curves (mean and 95% bootstrap CI over seeds) of run directories, in one figure."""

    runs: tyro.conf.Positional[tuple[Path, ...]]
    """Run directories to plot (their first hyperparameter set, or the best by AUC with --best)."""
    out: Path = Path("curves.png")
    """Image file to write."""
    best: bool = False
    """Plot each run's best hyperparameter set by AUC instead of its first."""
    undiscounted: bool = False
    """Plot undiscounted instead of discounted returns."""


@dataclasses.dataclass(frozen=True)
class Gap:
    """Memory-improvability gap: floor, GRU, λ-discrepancy, Transformer-XL and ceiling at the environment's preset,
    a table and a figure."""

    env: str = "tmaze_5"
    """Environment ID."""
    agents: tuple[str, ...] = AGENTS
    """Agents to train and report (floor, gru, ld, trxl, ceiling). Several processes may share one --out with
    different agents; a last call with all of them assembles the whole report from their finished runs."""
    memories: tuple[str, ...] = ()
    """Extra memory agents on the partial observation, besides gru/ld/trxl."""
    total_steps: int = 150_000
    """Environment steps per run."""
    num_seeds: int = 3
    """Seeds per agent."""
    hidden_size: int | None = None
    """Network width (default: the environment's recommended value)."""
    num_envs: int | None = None
    """Parallel environments per run (default: the environment's recommended value)."""
    out: Path | None = None
    """Output directory (default runs/gap-<env>-<time>): one run directory per agent, gap.json and gap.png."""
    sweep: bool = False
    """The paper's protocol: sweep step size × λ0 per agent, select by AUC, re-run the best with fresh seeds."""
    sweep_seeds: int = 5
    """Seeds per hyperparameter set in the sweep."""
    normalize_obs: bool = False
    """Normalise vector observations by running statistics (useful for MuJoCo)."""
    normalize_reward: bool = False
    """Scale rewards by the running std of the discounted return (useful for MuJoCo; logged returns stay raw)."""
    unroll: int | None = None
    """Unroll factor of the time loops (default: 1 on CPU, 4 on accelerators)."""
    quiet: bool = False
    """No progress output."""


@dataclasses.dataclass(frozen=True)
class Benchmark:
    """The benchmark: the gap report's five agents on a suite or list of environments at a named budget, into one
    results table (benchmark.csv, .md) and figure (benchmark.png). A second call with the same --out skips finished
    agents and resumes interrupted ones."""

    suite: Literal["discrete", "heavy", "paper"] | None = None
    """Environments: discrete (T-Maze, RockSample, Battleship, DMLab mazes), heavy (masked and pixel MuJoCo,
    Craftax) or paper (the paper's figure)."""
    envs: tuple[str, ...] = ()
    """Environments by ID, instead of --suite."""
    budget: Literal["smoke", "reduced", "paper"] = "reduced"
    """Steps and seeds per environment (registry): smoke (two updates of small networks: tests the machinery),
    reduced (the shipped results' budget), paper (the paper's steps, 30 seeds)."""
    agents: tuple[str, ...] = AGENTS
    """Agents per environment (floor, gru, ld, trxl, ceiling)."""
    memories: tuple[str, ...] = ()
    """Extra memory agents per environment."""
    out: Path | None = None
    """Output directory (default runs/benchmark-<budget>): results, one record per finished agent, run directories."""
    dry_run: bool = False
    """Print the plan (agents, steps, seeds, env steps in total) and stop."""
    quiet: bool = False
    """No progress output."""


@dataclasses.dataclass(frozen=True)
class Render:
    """Save the frames of one episode (random actions) of an image environment as a PNG grid."""

    env: str = "halfcheetah_pixels"
    """Environment ID with image observations (ant_pixels, halfcheetah_pixels, craftax_pixels, ...)."""
    steps: int = 32
    """Frames to render."""
    seed: int = 0
    """Random seed."""
    out: Path = Path("frames.png")
    """Image file to write."""
    cols: int = 8
    """Frames per row."""


@dataclasses.dataclass(frozen=True)
class Envs:
    """List the registered environments with their observabilities and categories."""


def _error(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


def _explicit_fields(argv: list[str]) -> set[str]:
    """TrainConfig fields given on the command line (as `--name`, `--no-name` or `--name=value`)."""
    names = set()
    for a in argv:
        if a.startswith("--"):
            name = a[2:].split("=", 1)[0]
            name = name[3:] if name.startswith("no-") else name
            names.add(name.replace("-", "_"))
    return names


def _train_config(cmd: Train, argv: list[str]) -> TrainConfig:
    from pobax.agent import apply_preset, resolve_preset

    cfg = TrainConfig(**{f.name: getattr(cmd, f.name) for f in dataclasses.fields(TrainConfig)})
    if cmd.preset is not None:
        cfg = apply_preset(cfg, resolve_preset(cmd.preset, cfg), keep=_explicit_fields(argv))
    return cfg


def _print_sets(summary: dict) -> None:
    sets = summary["sets"]
    swept = [k for k in NUMERIC if len({s[k] for s in sets}) > 1] or ["lr", "lambda0"]
    for s in sets:
        hp = ", ".join(f"{k}={s[k]:g}" for k in swept)
        d, u, a = s["disc_return"], s["return"], s["disc_return_auc"]
        print(f"  set {s['hp_index']} ({hp}): discounted {d['mean']:.3f} [{d['ci_low']:.3f}, {d['ci_high']:.3f}]"
              f"  undiscounted {u['mean']:.3f} [{u['ci_low']:.3f}, {u['ci_high']:.3f}]  AUC {a['mean']:.3f}")
    if len(sets) > 1:
        b = sets[summary["best_by_auc"]]
        print(f"best by AUC of the discounted return: set {b['hp_index']} ("
              + ", ".join(f"{k}={b[k]:g}" for k in swept) + ")")


def run_train(cmd: Train, argv: list[str]) -> None:
    from pobax.agent import train
    from pobax.agent._config import config_from_dict
    from pobax.eval import RunDir

    if cmd.resume is not None:
        saved = RunDir(cmd.resume).read_config()["config"] if (cmd.resume / "config.json").exists() else None
        if saved is None:
            _error(f"{str(cmd.resume)!r} is not a run directory (no config.json): nothing to resume.")
        cfg = config_from_dict(saved)
        result = train(cfg, cmd.resume, progress=not cmd.quiet, resume=True, max_chunks=cmd.max_chunks,
                       loggers=cmd.log)
    else:
        cfg = _train_config(cmd, argv)
        result = train(cfg, cmd.out, progress=not cmd.quiet, max_chunks=cmd.max_chunks, loggers=cmd.log)
    print(f"run directory: {result.run_dir}")
    if not result.summary["finished"]:
        print(f"stopped after --max-chunks; continue with: pobax train --resume {result.run_dir}")
    print(f"throughput: {result.steps_per_s:,.0f} env steps/s (all runs), compile ≈ {result.compile_s:.1f} s")
    print("final returns (last 10% of updates; mean [95% CI] over seeds):")
    _print_sets(result.summary)


def run_sweep(cmd: Sweep, argv: list[str]) -> None:
    from pobax.eval import sweep

    if cmd.resume is not None or cmd.max_chunks is not None:
        _error("sweep does not take --resume/--max-chunks: resume each program's run directory with `train --resume`.")
    cfg = _train_config(cmd, argv)
    report = sweep(cfg, out=cmd.out, axes=_parse_axes(cmd.axis), rerun_seeds=cmd.rerun_seeds,
                   progress=not cmd.quiet, max_runs=cmd.max_runs)
    print(f"sweep directory: {report['out']}")
    for p in report["programs"]:
        print(f"program {p['axis'] or '(base)'}: {p['run_dir']}")
        _print_sets(p["summary"])
    b = report["best"]
    print(f"selected by AUC: {b['axis'] or '(base)'} set {b['hp_index']} "
          + ", ".join(f"{k}={b['hyperparameters'][k]:g}" for k in NUMERIC) + f" -> preset {report['preset']}")
    if report.get("rerun"):
        r = report["rerun"]
        print(f"re-run with {cmd.rerun_seeds} fresh seeds: discounted {r['mean']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]")


def _parse_axes(items: tuple[str, ...]) -> dict[str, list]:
    from pobax.agent._config import FIELDS

    axes = {}
    for item in items:
        key, sep, values = item.partition("=")
        if not sep or not values:
            _error(f"--axis takes KEY=V1,V2,... (e.g. hidden_size=64,128), got {item!r}.")
        if key not in FIELDS or key in NUMERIC:
            hint = " (numeric hyperparameters are swept with their own flags, e.g. --lr 2.5e-3 2.5e-4)" if key in NUMERIC else ""
            _error(f"--axis {key!r} is not a structural TrainConfig field{hint}.")
        kind = type(getattr(TrainConfig(), key))
        try:
            axes[key] = [kind(v) if kind is not bool else v.lower() in ("1", "true", "yes") for v in values.split(",")]
        except ValueError:
            _error(f"--axis {key}: cannot read {values!r} as {kind.__name__} values.")
    return axes


def run_results(cmd: Results) -> None:
    from pobax.eval import list_runs

    rows = list_runs(cmd.root)
    if not rows:
        print(f"no runs under {cmd.root}")
        return
    print(f"{'run directory':58s} {'env':24s} {'agent':16s} {'obs':14s} {'sets×seeds':>10s} {'state':>9s} {'final disc. return':>22s}")
    for r in rows:
        ret = "" if r["disc_return"] is None else f"{r['disc_return']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]"
        print(f"{r['path']:58s} {r['env']:24s} {r['agent']:16s} {r['observability']:14s} "
              f"{r['sets']:>4d}×{r['seeds']:<5d} {r['state']:>9s} {ret:>22s}")


def run_plot(cmd: Plot) -> None:
    from pobax.eval import plot_runs

    path = plot_runs(cmd.runs, cmd.out, best=cmd.best, column="return" if cmd.undiscounted else "disc_return")
    print(f"figure: {path}")


def run_gap(cmd: Gap) -> None:
    from pobax.eval import format_gap, gap_report

    overrides = dict(total_steps=cmd.total_steps, num_seeds=cmd.num_seeds)
    if cmd.hidden_size is not None:
        overrides["hidden_size"] = cmd.hidden_size
    if cmd.num_envs is not None:
        overrides["num_envs"] = cmd.num_envs
    if cmd.unroll is not None:
        overrides["unroll"] = cmd.unroll
    if cmd.normalize_obs:
        overrides["normalize_obs"] = True
    if cmd.normalize_reward:
        overrides["normalize_reward"] = True
    report = gap_report(cmd.env, agents=cmd.agents, memories=cmd.memories, overrides=overrides, out=cmd.out,
                        progress=not cmd.quiet, sweep=cmd.sweep, sweep_seeds=cmd.sweep_seeds)
    print(format_gap(report))


def run_benchmark(cmd: Benchmark, argv: list[str]) -> None:
    import shlex

    from pobax.eval import run_benchmark as benchmark

    out = cmd.out if cmd.out is not None else Path("runs") / f"benchmark-{cmd.budget}"
    result = benchmark(cmd.envs, suite=cmd.suite, budget=cmd.budget, out=out, agents=cmd.agents,
                       memories=cmd.memories, progress=not cmd.quiet, dry_run=cmd.dry_run,
                       command="pobax benchmark " + shlex.join(argv[1:]))
    if not cmd.dry_run:
        print((out / "benchmark.md").read_text())
        print("results: " + ", ".join(str(f) for f in result["files"]))


def run_render(cmd: Render) -> None:
    from pobax.env import make, render_frames, save_frame_grid

    if cmd.steps < 1:
        _error(f"--steps must be a positive integer, got {cmd.steps}.")
    shape = make(cmd.env, wrappers=False).observation_space
    shape = getattr(shape, "shape", None)
    if shape is None or len(shape) != 3:
        _error(f"{cmd.env!r} has no image observation (shape {shape}); render one of the *_pixels environments.")
    frames = render_frames(cmd.env, cmd.steps, cmd.seed)
    cmd.out.parent.mkdir(parents=True, exist_ok=True)
    save_frame_grid(frames, str(cmd.out), cols=cmd.cols)
    print(f"{len(frames)} frames of {cmd.env} -> {cmd.out}")


def run_envs(cmd: Envs) -> None:
    from pobax.env._registry import _FAMILIES

    for f in _FAMILIES:
        ids = ", ".join(f.registered)
        print(f"{f.template:32s} observabilities: {', '.join(f.observabilities):32s} paper IDs: {ids}")
        print(f"{'':32s} categories: {', '.join(f.categories)}")


def main(argv: list[str] | None = None) -> None:
    from pobax.agent import ConfigError
    from pobax.eval import RunDirExistsError

    argv = sys.argv[1:] if argv is None else list(argv)
    cmd = tyro.extras.subcommand_cli_from_dict(
        {"train": Train, "sweep": Sweep, "gap": Gap, "benchmark": Benchmark, "results": Results, "plot": Plot,
         "render": Render, "envs": Envs},
        args=argv, description=__doc__,
    )
    if isinstance(cmd, (Train, Gap, Benchmark)):  # Sweep is a Train
        from pobax.agent import enable_compile_cache

        enable_compile_cache(accelerators_only=True)
    try:
        if isinstance(cmd, Sweep):
            run_sweep(cmd, argv)
        elif isinstance(cmd, Train):
            run_train(cmd, argv)
        elif isinstance(cmd, Results):
            run_results(cmd)
        elif isinstance(cmd, Plot):
            run_plot(cmd)
        elif isinstance(cmd, Render):
            run_render(cmd)
        elif isinstance(cmd, Gap):
            run_gap(cmd)
        elif isinstance(cmd, Benchmark):
            run_benchmark(cmd, argv)
        else:
            run_envs(cmd)
    except (ConfigError, RunDirExistsError, FileNotFoundError, ImportError) as e:
        _error(str(e))
    except ValueError as e:  # unknown environment, bad observability, bad environment parameter
        _error(str(e))


def entrypoint() -> None:
    main()


if __name__ == "__main__":
    main()
