"""The commands of the command line (`cli.py`): one frozen dataclass per command, its fields the flags and their
docstrings the help (tyro reads both), and `COMMANDS`, the table of their names."""

import dataclasses
from pathlib import Path
from typing import Annotated, Literal

import tyro

from ..agent import TrainConfig
from ..eval import AGENTS


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
    """Shard the runs over these devices (indices into `jax.devices()`; default: as many as the runs' environments
    fill, `pobax/_placement.py`)."""
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

    out: Path | None = None
    """Sweep directory (default: runs/sweep-<env>-<memory>-<time>); the same command with the same --out continues
    it, another sweep there is refused."""
    axis: tuple[str, ...] = ()
    """Structural axes, compiled one after another, e.g. `--axis hidden_size=64,128 num_envs=4,8` (not env,
    observability or seed: selection across them selects nothing of the agent)."""
    rerun_seeds: int = 0
    """Re-run the selected set with this many fresh seeds (the paper re-runs with 30) into <out>/rerun."""
    max_runs: int | None = None
    """Runs (sets × seeds) per compiled program (default: from a device-memory estimate): a larger grid is split along
    its longest hyperparameter axis, a part holding more where one value's runs alone are more (seeds are not
    split). A sweep continues only at the split it began with."""


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
    """Shard the runs over these devices (indices into `jax.devices()`; default: as many as the runs' environments
    fill, `pobax/_placement.py`)."""


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
    """Devices to use (indices into `jax.devices()`; default: every device, one job per GPU)."""
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
    """Directory for eval-<observability>-<policy>-seed<seed>.json (summary) and .csv (episodes), `-chunk<N>` added
    for an unfinished run's checkpoint; default: the run directory."""


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


COMMANDS = {"train": Train, "sweep": Sweep, "gap": Gap, "benchmark": Benchmark, "results": Results, "plot": Plot,
            "eval": Eval, "render": Render, "envs": Envs}
