"""pobax command line: `python cli.py <command> --help` (also installed as `pobax`).

Commands:
  train      train PPO agents (every combination of list-valued hyperparameters × seeds in one compiled program)
  sweep      sweep a grid, select the best set by AUC, write it as a preset file (and re-run it with fresh seeds)
  gap        memory-improvability gap report: floor, GRU, λ-discrepancy, Transformer-XL and ceiling on one environment
  benchmark  the gap report's agents on a suite of environments at a named budget: one results table and figure
  results    list the runs under a directory
  plot       learning curves with 95% CIs from any set of run directories
  eval       play fresh episodes with the trained agents of a run directory: returns with 95% CIs, lengths, metrics
  render     watch one episode of a trained agent (GIF + PNG strip, with its memory), or random actions (--env)
  envs       list the registered environments

Training options (`--lr`, `--hidden-size`, ...) are `pobax.agent.TrainConfig`'s fields for every command that trains.
"""

import dataclasses
import os
import shlex
import signal
import sys
import threading
import typing
from pathlib import Path
from typing import Annotated, Literal

# A Ctrl-C while the imports below load JAX (about a second) is noted and honoured once they are done: a
# KeyboardInterrupt in the middle of an import would print a traceback, or be dropped by a callback.
_CTRL_C: list = []
_HOOKED = threading.current_thread() is threading.main_thread() and \
    signal.getsignal(signal.SIGINT) is signal.default_int_handler
if _HOOKED:
    signal.signal(signal.SIGINT, lambda *_: _CTRL_C.append(True))

import tyro  # noqa: E402

from pobax.agent import NUMERIC, TrainConfig  # noqa: E402
from pobax.eval import AGENTS  # noqa: E402

if _HOOKED:
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if _CTRL_C:
        print("error: interrupted", file=sys.stderr)
        raise SystemExit(130)

_TRAIN_FIELDS = {f.name for f in dataclasses.fields(TrainConfig)}


@dataclasses.dataclass(frozen=True)
class Train(TrainConfig):
    """Train PPO agents on one environment; list values (e.g. `--lr 2.5e-3 2.5e-4`) are swept together."""

    out: Path | None = None
    """Run directory (default: runs/<env>-<observability>-<memory>-<time>). Must not already hold results."""
    quiet: bool = False
    """No progress output."""
    preset: str | None = None
    """`paper`: the environment's recommended settings and best hyperparameters for this agent (the paper's tables,
    with the registry's documented deviations); `paper-original`: the paper's tables as printed; or a preset JSON
    file (e.g. `best.json` from `sweep`). Flags given explicitly override the preset."""
    resume: Path | None = None
    """Continue the interrupted run in this directory with its saved configuration (training flags are refused)."""
    max_chunks: int | None = None
    """Stop after this many chunks, leaving a run that `--resume` continues."""
    log: tuple[str, ...] = ()
    """Also log to these trackers when installed: tensorboard (into <run>/tensorboard), wandb."""
    devices: tuple[int, ...] = ()
    """Shard the runs over these devices (indices into `jax.devices()`; default: every device)."""
    coordinator: str | None = None
    """Multi-process run (train only): process 0's HOST:PORT, with --num-processes and --process-id; the same
    command in every process, which shard the runs over all their devices (process 0 writes the run directory)."""
    num_processes: int | None = None
    """Multi-process run: the number of processes."""
    process_id: int | None = None
    """Multi-process run: this process's index, 0 .. num_processes - 1."""
    distributed: bool = False
    """Multi-process run with the coordinator, process count and index from the cluster (e.g. under SLURM's srun)."""


@dataclasses.dataclass(frozen=True)
class Sweep(Train):
    """Train a grid (list-valued hyperparameters × seeds in one program; `--axis` values as separate programs),
    select the set with the largest area under the discounted learning curve, and write it as `best.json`. The same
    command with the same `--out` continues an interrupted sweep (finished programs are reused)."""

    axis: tuple[str, ...] = ()
    """Structural axes, compiled one after another, e.g. `--axis hidden_size=64,128 num_envs=4,8`."""
    rerun_seeds: int = 0
    """Re-run the selected set with this many fresh seeds (the paper re-runs with 30) into <out>/rerun."""
    max_runs: int | None = None
    """Runs (sets × seeds) per compiled program; larger grids are split (default: from a device-memory estimate)."""


@dataclasses.dataclass(frozen=True)
class Gap(TrainConfig):
    """Memory-improvability gap: floor, GRU, λ-discrepancy, Transformer-XL and ceiling at the environment's preset,
    a table and a figure. Training flags given explicitly override every agent's preset."""

    env: str = "tmaze_5"
    """Environment ID."""
    total_steps: int = 150_000
    """Environment steps per run (the default is sized for the quick start on T-Maze 5; `pobax benchmark` trains each
    environment at its budget)."""
    num_seeds: int = 5
    """Seeds per agent."""
    agents: tuple[str, ...] = AGENTS
    """Agents to train and report (floor, gru, ld, trxl, ceiling). Several processes may share one --out with
    different agents; a last call with all of them assembles the whole report from their finished runs."""
    memories: tuple[str, ...] = ()
    """Extra memory agents on the partial observation, besides gru/ld/trxl: the zoo (lstm lru s6 ffm) or your own
    cell as package.module:ClassName; preset: the GRU's unless the registry has one for the memory."""
    out: Path | None = None
    """Output directory (default runs/gap-<env>-<time>): one run directory per agent, gap.json and gap.png."""
    sweep: bool = False
    """Sweep step size × λ0 per agent at the registry's other settings, select by AUC, re-run the best with fresh
    seeds."""
    protocol: Literal["registry", "paper"] = "registry"
    """registry: each agent at the registry's settings (or --sweep). paper: the paper's protocol per agent (its fixed
    settings and steps, its sweep grid and selection seeds, selection by AUC, the selected set on --num-seeds fresh
    seeds, 30 unless given; the paper's ceiling), as `pobax benchmark --protocol paper --envs ENV --budget paper`."""
    sweep_seeds: int = 5
    """Seeds per hyperparameter set in the sweep."""
    quiet: bool = False
    """No progress output."""
    devices: tuple[int, ...] = ()
    """Shard the runs over these devices (indices into `jax.devices()`; default: every device)."""


@dataclasses.dataclass(frozen=True)
class Benchmark(TrainConfig):
    """The benchmark: the gap report's five agents on a suite or list of environments at a named budget, into one
    results table (benchmark.csv, .md) and figure (benchmark.png). A second call with the same --out skips finished
    agents and resumes interrupted ones. Training flags given explicitly override every agent's preset and budget."""

    suite: Literal["discrete", "heavy", "paper"] | None = None
    """Environments: discrete (T-Maze, RockSample, Battleship, DMLab mazes), heavy (masked and pixel MuJoCo,
    Craftax) or paper (the paper's figure)."""
    envs: tuple[str, ...] = ()
    """Environments by ID, instead of --suite."""
    budget: Literal["smoke", "reduced", "paper"] = "reduced"
    """Steps and seeds per environment (registry): smoke (three updates of small networks: tests the machinery),
    reduced (the shipped results' budget), paper (the paper's steps, 30 seeds)."""
    agents: tuple[str, ...] = AGENTS
    """Agents per environment (floor, gru, ld, trxl, ceiling)."""
    memories: tuple[str, ...] = ()
    """Extra memory agents per environment: the zoo (lstm lru s6 ffm) or package.module:ClassName (see gap)."""
    out: Path | None = None
    """Output directory (default runs/benchmark-<budget>): results, one record per finished agent, run directories."""
    dry_run: bool = False
    """Print the plan (agents, steps, seeds, env steps in the plan and left to train: an interrupted run's chunks
    done and a sweep's finished parts are not counted again; under the paper's protocol the GPU time left, at the rate
    of its finished parts or, marked ~, of an agent of the same memory and sizes) and stop."""
    quiet: bool = False
    """No progress output."""
    devices: tuple[int, ...] = ()
    """Devices to use (indices into `jax.devices()`; default: every device)."""
    jobs: int | None = None
    """Agents trained at once, each in a process of its own on one of --devices (its output in runs/ENV/NAME.log;
    more jobs than devices share them). 1: one agent at a time, its runs sharded over --devices. Default: one job per
    GPU on a machine with several GPUs, else 1."""
    protocol: Literal["registry", "paper"] = "registry"
    """registry: each agent at the registry's settings and the budget's seeds. paper: the paper's protocol per agent
    (its fixed settings, its sweep grid on its selection seeds, selection by AUC, the selected set rerun on 30 fresh
    seeds; the paper's ceiling, and the registry's as ceiling_pobax where it differs), at the budget's steps."""
    part_steps: int | None = None
    """--protocol paper: the most env steps of one program of a sweep (default 300,000,000: RockSample's and
    Battleship's sweeps train as parts of minutes on one GPU, which side-by-side jobs train at once and an
    interrupted call keeps); 0: each sweep in one program."""
    merge: tuple[Path, ...] = ()
    """Instead of training: copy the finished agents' records of these benchmark output directories (e.g. from
    other machines) into --out, keeping any record --out already has, and write the results."""


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
    """Image file to write (a .png name; a directory gets curves.png inside)."""
    best: bool = False
    """Plot each run's best hyperparameter set by AUC instead of its first."""
    undiscounted: bool = False
    """Plot undiscounted instead of discounted returns."""
    metric: str | None = None
    """Plot a training metric of the runs' metrics/*.csv instead of the return, e.g. entropy (the policy's),
    ep_length, approx_kl, clip_frac, v_loss, value_mean."""
    json: Path | None = None
    """Also write the curves as JSON: per run, env steps, mean and 95% CI over seeds, and each seed's values."""


@dataclasses.dataclass(frozen=True)
class Eval:
    """Play fresh episodes with every trained agent (hyperparameter set × seed) of a run directory, finished or
    interrupted (its last checkpoint); print and write the returns (discounted and undiscounted; mean and 95% CI
    over seeds), episode lengths and the environment's episode metrics."""

    run: tyro.conf.Positional[Annotated[Path, tyro.conf.arg(metavar="RUN_DIR")]]
    """Run directory (written by `pobax train`)."""
    episodes: int = 10
    """Episodes per run."""
    greedy: bool = False
    """Take the most probable action instead of sampling from the policy."""
    observability: str | None = None
    """Play another observability of the environment (default: the one trained on); its observations must have
    the shape the network was trained on."""
    seed: int = 0
    """Random seed of the episodes (the same episodes for every run; the same results for the same seed)."""
    max_steps: int | None = None
    """Cut episodes after this many steps (default: the environment's time limit)."""
    out: Path | None = None
    """Directory for eval-<observability>-<policy>-seed<seed>.json (summary) and .csv (episodes); default: the run
    directory."""


@dataclasses.dataclass(frozen=True)
class Render:
    """Watch an agent. With RUN_DIR: one episode of a trained agent as an animated GIF and a PNG strip of frames,
    the environment drawn beside the memory's state. With --env: a PNG grid of frames under random actions (an image
    environment's observations; a DMLab maze drawn as for a trained agent)."""

    run: tyro.conf.Positional[Annotated[Path | None, tyro.conf.arg(metavar="RUN_DIR")]] = None
    """Run directory of the trained agent to watch."""
    env: str | None = None
    """Without RUN_DIR: environment ID with image observations (ant_pixels, halfcheetah_pixels (default),
    craftax_pixels, ...) or a DMLab maze (Navix-DMLab-Maze-01-v0, ...)."""
    steps: int | None = None
    """Frames under random actions (default 32, at most 1,024: one PNG grid); with RUN_DIR, the most steps of the
    episode shown (default 200; the environment's time limit at most)."""
    seed: int = 0
    """Random seed (with RUN_DIR: the episode is episode 0 of `pobax eval` with this seed)."""
    out: Path | None = None
    """With RUN_DIR: a .gif (the strip is written beside it as .png; default <RUN_DIR>/episode.gif) or a .png (the
    strip only). With --env: the PNG grid (default frames.png)."""
    cols: int = 8
    """With --env: frames per row (1 to 1,024)."""
    set: int | None = None
    """With RUN_DIR: the hyperparameter set to watch (default: the best by AUC)."""
    run_seed: int = 0
    """With RUN_DIR: the seed index of the run to watch."""
    greedy: bool = False
    """With RUN_DIR: take the most probable action instead of sampling."""
    observability: str | None = None
    """With RUN_DIR: play another observability of the environment (same observation shape)."""


@dataclasses.dataclass(frozen=True)
class Envs:
    """List the registered environments with their observabilities and categories."""


class UsageError(ValueError):
    """A command line that cannot run: printed as one line, exit 2."""


def _shifted(value, hint):
    """A value of the field type `hint` that differs from `value` (`_given_fields`)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is Literal:
        return next(a for a in args if a != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, tuple) and typing.get_args(hint)[:1] == (str,):  # tuple[str, ...]
        return (*value, "~")
    if isinstance(value, tuple):
        return tuple(v + 1 for v in value) or (1.0,)
    if isinstance(value, str):
        return value + "~"
    return 1  # None, in an `int | None` field


def _given_fields(cmd, argv: list[str]) -> frozenset[str]:
    """The TrainConfig fields given on the command line, as tyro reads it: the same arguments parsed again over
    defaults that all differ from the real ones. A field given has the same value in both parses; one left to its
    default differs. (A field given with its default value counts as given: it overrides a preset.)"""
    cls = type(cmd)
    hints = typing.get_type_hints(cls)
    shifted = {f.name: _shifted(f.default, hints[f.name]) if f.default is not dataclasses.MISSING else
               _shifted(f.default_factory(), hints[f.name]) for f in dataclasses.fields(cls) if f.name in _TRAIN_FIELDS}
    again = tyro.cli(cls, args=argv, default=dataclasses.replace(cls(), **shifted))
    return frozenset(k for k in _TRAIN_FIELDS if getattr(again, k) == getattr(cmd, k))


def _overrides(cmd, given: frozenset[str], per_agent: tuple[str, ...] = ()) -> dict:
    """The training flags given explicitly, as overrides of every agent's preset; `per_agent` fields are refused."""
    explicit = given
    refused = sorted(explicit & set(per_agent))
    if refused:
        raise UsageError(f"--{refused[0].replace('_', '-')} is set per agent by this command; choose agents with "
                         f"--agents (and --memories) instead.")
    return {k: getattr(cmd, k) for k in explicit}


def _train_config(cmd: Train, given: frozenset[str]) -> TrainConfig:
    from pobax.agent import apply_preset, resolve_preset

    cfg = TrainConfig(**{name: getattr(cmd, name) for name in _TRAIN_FIELDS})
    if cmd.preset not in (None, "paper", "paper-original") and Path(cmd.preset).is_dir():
        raise UsageError(f"--preset {cmd.preset!r} is a directory; pass a preset file (e.g. best.json, which sweep "
                         f"writes), paper or paper-original.")
    if cmd.preset is not None:
        cfg = apply_preset(cfg, resolve_preset(cmd.preset, cfg), keep=set(given))
    return cfg


def _devices(indices: tuple[int, ...]) -> list | None:
    """The devices of `--devices` (None: every device)."""
    if not indices:
        return None
    import jax

    devs = jax.devices()
    bad = [i for i in indices if not 0 <= i < len(devs)]
    if bad:
        raise UsageError(f"--devices {bad[0]}: the device indices are 0 .. {len(devs) - 1} "
                         f"({', '.join(str(d) for d in devs)}).")
    if len(set(indices)) < len(indices):
        raise UsageError("--devices names a device twice.")
    return [devs[i] for i in indices]


def _distributed(cmd) -> None:
    """Join a multi-process run if the command line asks for one (before anything else uses JAX)."""
    if not isinstance(cmd, Train) or not (cmd.distributed or cmd.coordinator is not None
                                          or cmd.num_processes is not None or cmd.process_id is not None):
        return
    if isinstance(cmd, Sweep):
        raise UsageError("sweep runs in one process (over every local device); a multi-process run is `pobax "
                         "train`'s: train the grid with it, then select with `pobax results`.")
    from pobax import init_distributed

    if cmd.distributed and cmd.num_processes is not None:
        raise UsageError("--distributed reads the processes from the cluster; drop --num-processes/--process-id.")
    try:
        init_distributed(cmd.coordinator, cmd.num_processes, cmd.process_id)
    except RuntimeError as e:
        raise UsageError(f"cannot join the multi-process run: {str(e).splitlines()[0] if str(e) else e}") from None


def _print_sets(summary: dict) -> None:
    sets = summary["sets"]
    swept = [k for k in NUMERIC if len({s[k] for s in sets}) > 1] or ["lr", "lambda0"]
    for s in sets:
        hp = ", ".join(f"{k}={s[k]:g}" for k in swept)
        d, u, a = s["disc_return"], s["return"], s["disc_return_auc"]
        diverged = f"  ({s['diverged']} of {s['num_seeds']} seeds diverged, left out)" if s.get("diverged") else ""
        print(f"  set {s['hp_index']} ({hp}): discounted {d['mean']:.3f} [{d['ci_low']:.3f}, {d['ci_high']:.3f}]"
              f"  undiscounted {u['mean']:.3f} [{u['ci_low']:.3f}, {u['ci_high']:.3f}]  AUC {a['mean']:.3f}{diverged}")
    if len(sets) > 1:
        b = sets[summary["best_by_auc"]]
        print(f"best by AUC of the discounted return: set {b['hp_index']} ("
              + ", ".join(f"{k}={b[k]:g}" for k in swept) + ")"
              + (" — every set has a diverged run" if summary.get("all_sets_diverged") else ""))


def run_train(cmd: Train, given: frozenset[str], on_chunk=None) -> None:
    from pobax.agent import config_from_dict
    from pobax.eval import RunDir, train
    from pobax.eval._run import default_out

    if cmd.resume is not None:
        flags = sorted(given | ({"preset"} if cmd.preset else set()) | ({"out"} if cmd.out else set()))
        if flags:
            raise UsageError(f"--resume continues the run with its saved configuration; drop "
                             f"{', '.join('--' + f.replace('_', '-') for f in flags)}.")
        if not (cmd.resume / "config.json").exists():
            raise UsageError(f"{str(cmd.resume)!r} is not a run directory (no config.json): nothing to resume.")
        saved = RunDir(cmd.resume).read_config().get("config", {})
        cfg, out = config_from_dict(saved, source=f"{str(cmd.resume / 'config.json')!r}"), cmd.resume
    else:
        cfg = _train_config(cmd, given)
        out = cmd.out if cmd.out is not None else default_out(cfg)
    started = None if cmd.quiet else lambda path: print(f"run directory: {path}", flush=True)  # once it is claimed
    result = train(cfg, out, progress=not cmd.quiet, resume=cmd.resume is not None, max_chunks=cmd.max_chunks,
                   loggers=cmd.log, on_start=started, on_chunk=on_chunk, devices=_devices(cmd.devices))
    import jax

    if jax.process_index() != 0:  # another process of a multi-process run: process 0 reports
        return
    print(f"run directory: {result.run_dir}")
    if not result.summary["finished"]:
        print(f"stopped after --max-chunks; continue with: pobax train --resume {shlex.quote(str(result.run_dir))}")
    if result.steps_per_s == result.steps_per_s:  # NaN after a single chunk: no steady chunk to time
        print(f"throughput: {result.steps_per_s:,.0f} env steps/s (all runs), compile ≈ {result.compile_s:.1f} s")
    print("final returns (last 10% of updates; mean [95% CI] over seeds):")
    _print_sets(result.summary)


def run_sweep(cmd: Sweep, given: frozenset[str], on_chunk=None) -> None:
    from pobax.eval import sweep

    if cmd.resume is not None or cmd.max_chunks is not None:
        raise UsageError("sweep does not take --resume/--max-chunks: run the same sweep with the same --out to "
                         "continue it.")
    cfg = _train_config(cmd, given)
    report = sweep(cfg, out=cmd.out, axes=_parse_axes(cmd.axis), rerun_seeds=cmd.rerun_seeds,
                   progress=not cmd.quiet, max_runs=cmd.max_runs, devices=_devices(cmd.devices), on_chunk=on_chunk)
    print(f"sweep directory: {report['out']}")
    for p in report["programs"]:
        print(f"program {p['axis'] or '(base)'}: {p['run_dir']}")
        _print_sets(p["summary"])
    b = report["best"]
    print(f"selected by AUC: {b['axis'] or '(base)'} set {b['hp_index']} "
          + ", ".join(f"{k}={b['hyperparameters'][k]:g}" for k in NUMERIC) + f" -> preset {report['preset']}"
          + (f" (every set has a diverged run; this one {b['diverged']} of {b['num_seeds']} seeds)"
             if b.get("diverged") else ""))
    if report.get("rerun"):
        r = report["rerun"]
        print(f"re-run with {cmd.rerun_seeds} fresh seeds: discounted {r['mean']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]")


def _parse_axes(items: tuple[str, ...]) -> dict[str, list]:
    axes = {}
    for item in items:
        key, sep, values = item.partition("=")
        if not sep or not values:
            raise UsageError(f"--axis takes KEY=V1,V2,... (e.g. hidden_size=64,128), got {item!r}.")
        if key not in _TRAIN_FIELDS or key in NUMERIC:
            hint = " (numeric hyperparameters are swept with their own flags, e.g. --lr 2.5e-3 2.5e-4)" if key in NUMERIC else ""
            raise UsageError(f"--axis {key!r} is not a structural TrainConfig field{hint}.")
        kind = type(getattr(TrainConfig(), key))
        try:
            axes[key] = [kind(v) if kind is not bool else v.lower() in ("1", "true", "yes") for v in values.split(",")]
        except ValueError:
            raise UsageError(f"--axis {key}: cannot read {values!r} as {kind.__name__} values.") from None
    return axes


def run_results(cmd: Results) -> None:
    from pobax.eval import list_runs

    if not cmd.root.is_dir():
        raise UsageError(f"--root {str(cmd.root)!r} is not a directory.")
    rows = list_runs(cmd.root)
    if not rows:
        print(f"no runs under {cmd.root}")
        return
    print(f"{'run directory':58s} {'env':24s} {'agent':16s} {'obs':14s} {'sets×seeds':>10s} {'state':>9s} {'final disc. return':>22s}")
    for r in rows:
        ret = (f"{r['disc_return']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]" if r["disc_return"] is not None
               else "no episode ended" if r["state"] == "finished" else "")
        print(f"{r['path']:58s} {r['env']:24s} {r['agent']:16s} {r['observability']:14s} "
              f"{r['sets']:>4d}×{r['seeds']:<5d} {r['state']:>9s} {ret:>22s}")
    for r in rows:  # after the table, which stays one row per run: what is damaged and why
        if r.get("problem"):
            print(f"damaged: {r['problem']}", file=sys.stderr)


def _output_file(path: Path, flag: str = "--out") -> Path:
    """`path` as a file to write, its folder created; a one-line error if an existing parent is a file or the folder
    cannot be made."""
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
    out = _output_file(cmd.out / "curves.png" if cmd.out.is_dir() else cmd.out)
    data = None if cmd.json is None else _output_file(cmd.json, "--json")
    column = cmd.metric or ("return" if cmd.undiscounted else "disc_return")
    path = plot_runs(cmd.runs, out, best=cmd.best, column=column, data=data)
    print(f"figure: {path}" + (f"\ncurves: {data}" if data is not None else ""))


def gap_steps_note(env: str, total_steps: int) -> str | None:
    """A line after a `gap` run at its default `--total-steps` where the environment's benchmark budget (`reduced`)
    trains longer: the default is sized for the quick start (T-Maze 5 in CPU minutes), and a sweep selected on it
    selects for the first steps only."""
    from pobax.env import spec

    budget = spec(env).budget("reduced")
    if budget["total_steps"] <= total_steps:
        return None
    return (f"note: {total_steps:,} steps per run (--total-steps); {env}'s benchmark budget is "
            f"{budget['total_steps']:,} steps × {budget['num_seeds']} seeds (`pobax benchmark --envs {env}`)")


def run_gap(cmd: Gap, given: frozenset[str], argv: list[str], on_chunk=None) -> None:
    from pobax.eval import format_gap, gap_report

    if cmd.protocol == "paper":
        from pobax.eval import run_benchmark as benchmark

        if cmd.sweep:
            raise UsageError("--protocol paper sweeps the paper's grid itself: drop --sweep.")
        out = cmd.out if cmd.out is not None else Path("runs") / f"gap-{cmd.env}-paper-protocol"
        overrides = _overrides(cmd, given - {"env"}, per_agent=("memory", "observability", "double_critic",
                                                                "encoder"))
        result = benchmark((cmd.env,), budget="paper", out=out, agents=cmd.agents, memories=cmd.memories,
                           overrides=overrides, progress=not cmd.quiet, command="pobax " + shlex.join(argv),
                           devices=_devices(cmd.devices), protocol="paper", on_chunk=on_chunk)
        print((out / "benchmark.md").read_text())
        print("results: " + ", ".join(str(f) for f in result["files"]))
        return

    overrides = {"total_steps": cmd.total_steps, "num_seeds": cmd.num_seeds,
                 **_overrides(cmd, given, per_agent=("memory", "observability", "double_critic", "encoder"))}
    report = gap_report(cmd.env, agents=cmd.agents, memories=cmd.memories, overrides=overrides, out=cmd.out,
                        progress=not cmd.quiet, sweep=cmd.sweep, sweep_seeds=cmd.sweep_seeds,
                        devices=_devices(cmd.devices), on_chunk=on_chunk)
    print(format_gap(report))
    # after the verdict it qualifies (before it, a refused command would print two lines)
    if "total_steps" not in given and (note := gap_steps_note(cmd.env, cmd.total_steps)):
        print(note, file=sys.stderr, flush=True)


def _part_steps(cmd: Benchmark) -> dict:
    """--part-steps as run_benchmark's argument: none given, its default; 0, None (each sweep whole)."""
    if cmd.part_steps is None:
        return {}
    if cmd.part_steps < 0:
        raise UsageError(f"--part-steps must be 0 (each sweep in one program) or more, got {cmd.part_steps}.")
    if cmd.protocol != "paper":
        raise UsageError("--part-steps splits the sweeps of --protocol paper; the registry's protocol has none.")
    return {"part_steps": cmd.part_steps or None}


def run_benchmark(cmd: Benchmark, given: frozenset[str], argv: list[str], on_chunk=None) -> None:
    from pobax.eval import run_benchmark as benchmark

    out = cmd.out if cmd.out is not None else Path("runs") / f"benchmark-{cmd.budget}"
    if cmd.merge:
        from pobax.eval import merge_results

        if cmd.envs or cmd.suite:
            raise UsageError("--merge trains nothing: drop --envs / --suite (the records come from the merged "
                             "directories).")
        result = merge_results(out, cmd.merge, command="pobax " + shlex.join(argv))
        for name in result["kept"]:
            print(f"kept {out}'s record of {name}: a merged directory's differs", file=sys.stderr)
        for name in result["kept_parts"]:
            print(f"kept {out}'s sweep part {name}: a merged directory's has another configuration", file=sys.stderr)
        print((out / "benchmark.md").read_text())
        n, k = len(result["added"]), len(result["parts"])
        parts = f" and {k} finished sweep part{'s' * (k != 1)} (the protocol continues from them)" if k else ""
        print(f"merged {n} record{'s' * (n != 1)}{parts} into {out}"
              + (": " + ", ".join(result["added"]) if result["added"] else ""))
        print("results: " + ", ".join(str(f) for f in result["files"]))
        return
    overrides = _overrides(cmd, given, per_agent=("env", "memory", "observability", "double_critic", "encoder"))
    result = benchmark(cmd.envs, suite=cmd.suite, budget=cmd.budget, out=out, agents=cmd.agents,
                       memories=cmd.memories, overrides=overrides, progress=not cmd.quiet, dry_run=cmd.dry_run,
                       command="pobax " + shlex.join(argv), devices=_devices(cmd.devices), jobs=cmd.jobs,
                       protocol=cmd.protocol, on_chunk=on_chunk, **_part_steps(cmd))
    if not cmd.dry_run:
        print((out / "benchmark.md").read_text())
        print("results: " + ", ".join(str(f) for f in result["files"]))


def run_eval(cmd: Eval) -> None:
    from pobax.agent import config_from_dict
    from pobax.eval import RunDir, evaluate, format_eval
    from pobax.eval._bounds import check_eval_fits

    if (cmd.run / "config.json").is_file():  # (else evaluate says what is wrong with the path)
        record = RunDir(cmd.run).read_config()
        cfg = config_from_dict(record.get("config", {}), source=repr(str(cmd.run / "config.json")))
        check_eval_fits(cmd.episodes, cfg, len(record.get("hyperparameter_sets", [])) * cfg.num_seeds)

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
              + ", ".join(str(p) for p in (r.gif, r.png) if p is not None))
        return
    env = cmd.env or "halfcheetah_pixels"
    from pobax.eval._render import has_picture, random_frames

    if has_picture(env):  # a maze: drawn as a trained agent's episode is
        import numpy as np

        out = _output_file(cmd.out or Path("frames.png"))
        frames = np.stack(random_frames(env, cmd.steps or 32, cmd.seed))
        save_frame_grid(frames, str(out), cols=cmd.cols, scale=1)
        print(f"{len(frames)} frames of {env} -> {out}")
        return
    shape = getattr(make(env, wrappers=False).observation_space, "shape", None)
    if shape is None or len(shape) != 3:
        raise UsageError(f"{env!r} has no image observation (shape {shape}); render one of the *_pixels "
                         f"environments, or a trained agent: pobax render RUN_DIR.")
    out = _output_file(cmd.out or Path("frames.png"))
    frames = render_frames(env, cmd.steps or 32, cmd.seed)
    save_frame_grid(frames, str(out), cols=cmd.cols)
    print(f"{len(frames)} frames of {env} -> {out}")


def run_envs(cmd: Envs) -> None:
    from pobax.env._registry import _FAMILIES

    for f in _FAMILIES:
        ids = ", ".join(f.registered)
        print(f"{f.template:32s} observabilities: {', '.join(f.observabilities):32s} paper IDs: {ids}")
        print(f"{'':32s} categories: {', '.join(f.categories)}")


COMMANDS = {"train": Train, "sweep": Sweep, "gap": Gap, "benchmark": Benchmark, "results": Results, "plot": Plot,
            "eval": Eval, "render": Render, "envs": Envs}


def _error(msg: str, code: int = 2) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(code)


def main(argv: list[str] | None = None, *, on_chunk=None) -> None:
    """Run the command line `argv` (default: this process's), e.g. `main(["train", "--env", "tmaze_5"])`. `on_chunk`:
    called with every chunk that the command trains (train, sweep, gap, benchmark; `pobax.train`'s `on_chunk`), e.g.
    to follow a command run from Python; the benchmark then trains in this process (one job)."""
    from pobax.eval import BenchmarkFailed, Interrupted

    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        cmd = tyro.extras.subcommand_cli_from_dict(COMMANDS, args=argv, description=__doc__)
    except ValueError as e:  # a type check of TrainConfig (e.g. a preset-like value given as a flag)
        _error(str(e))
    sub = argv[1:] if argv else []
    try:
        _distributed(cmd)
    except ValueError as e:  # a UsageError, or init_distributed's
        _error(str(e))
    training = type(cmd) in (Train, Sweep, Gap, Benchmark)
    if type(cmd) is Benchmark and cmd.jobs != 1 and not cmd.dry_run:
        # Agents side by side (several GPUs) run in processes of their own: this one must not hold most of every
        # GPU's memory, as JAX's preallocation would once its backend starts (the next lines start it). Every
        # agent of results/ was trained with preallocation off (benchmarks/device_benchmark.sh).
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if training:
        from pobax.agent import enable_compile_cache

        enable_compile_cache(accelerators_only=True)
    given = _given_fields(cmd, sub) if training else frozenset()
    handlers = {  # by the command's exact class (Sweep is a Train: an isinstance chain would depend on its order)
        Train: lambda: run_train(cmd, given, on_chunk), Sweep: lambda: run_sweep(cmd, given, on_chunk),
        Gap: lambda: run_gap(cmd, given, argv, on_chunk), Benchmark: lambda: run_benchmark(cmd, given, argv, on_chunk),
        Results: lambda: run_results(cmd),
        Plot: lambda: run_plot(cmd), Eval: lambda: run_eval(cmd), Render: lambda: run_render(cmd),
        Envs: lambda: run_envs(cmd),
    }
    try:
        handlers[type(cmd)]()
    except Interrupted as e:
        if type(cmd) in (Gap, Benchmark):
            _error("interrupted; the same command with the same --out continues (finished agents are kept, the "
                   "interrupted one resumes from its last checkpoint).", 130)
        if type(cmd) is Sweep:
            _error("interrupted; the same sweep command with the same --out continues (finished programs are kept, "
                   "the interrupted one resumes from its last checkpoint).", 130)
        resume = f"pobax train --resume {shlex.quote(str(e.run_dir))}" if e.run_dir is not None else ""
        where = "" if not resume else (f"; the last checkpoint is in {e.run_dir}: continue with {resume}" if e.checkpoint
                                       else f" before the first checkpoint of {e.run_dir}: start it again with {resume}")
        _error(f"interrupted{where}", 130)
    except KeyboardInterrupt:
        _error("interrupted", 130)
    except BenchmarkFailed as e:  # agents trained side by side that failed; the others' results are written
        _error(str(e), 1)
    except BrokenPipeError:  # stdout's reader has gone (`pobax results | head -1`): `entrypoint` ends quietly
        raise
    except OSError as e:  # a file-system problem (a path, permissions, a full disk)
        _error(str(e).splitlines()[0] if str(e) else type(e).__name__)
    except RuntimeError as e:  # XLA out of memory where the bound checked before compiling (a lower bound) passed
        first = str(e).splitlines()[0] if str(e) else ""
        if "RESOURCE_EXHAUSTED" not in first:
            raise
        _error(f"out of device memory ({first}); lower --num-envs, --hidden-size or the runs of one program (seeds "
               "× sets; `sweep --max-runs`), or free the device; files already written are kept")
    except (ValueError, ImportError) as e:
        if not _raised_by_pobax(e):  # an internal error in the user's code (a memory cell): its traceback matters
            raise
        _error(str(e).splitlines()[0] if str(e) else type(e).__name__)  # bad input, a missing extra


def _raised_by_pobax(e: BaseException) -> bool:
    """Whether `e` was raised by pobax's own code (this file or the package): a refusal of bad input, which it says
    in a line, rather than an error inside code pobax calls (a user's memory cell, a library)."""
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is None:
        return True
    where = Path(tb.tb_frame.f_code.co_filename).resolve()
    return where == Path(__file__).resolve() or _PACKAGE in where.parents


_PACKAGE = Path(__import__("pobax").__file__).resolve().parent


def entrypoint() -> None:
    try:
        main()
    except BrokenPipeError:  # stdout's reader stopped early (`pobax train --help | head -1`): Python's recipe
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (the last flush at exit fails no more)
        raise SystemExit(1) from None
    except KeyboardInterrupt:  # before a command started (reading the command line)
        print("error: interrupted", file=sys.stderr)
    except SystemExit as e:
        if e.code != 130:
            raise
    else:
        return
    # Ctrl-C: XLA may still be compiling or running in its threads, and tearing the interpreter down under them can
    # crash it (a segmentation fault instead of exit 130); every file is already written whole.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(130)


if __name__ == "__main__":
    entrypoint()
