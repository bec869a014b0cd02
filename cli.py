"""pobax command line: `python cli.py <command> --help` (also installed as `pobax`).

Commands:
  train   train PPO agents (every combination of list-valued hyperparameters × seeds in one compiled program)
  gap     memory-improvability gap report: floor (memoryless, partial), memory agents, ceiling (full state)
  envs    list the registered environments
"""

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import tyro

from pobax.agent import NUMERIC, TrainConfig


@dataclasses.dataclass(frozen=True)
class Train(TrainConfig):
    """Train PPO agents on one environment; list values (e.g. `--lr 2.5e-3 2.5e-4`) are swept together."""

    out: Path | None = None
    """Run directory (default: runs/<env>-<observability>-<memory>-<time>). Must not already hold results."""
    quiet: bool = False
    """No progress output."""


@dataclasses.dataclass(frozen=True)
class Gap:
    """Memory-improvability gap: floor, memory agents and ceiling with the paper's hyperparameters, a table and a figure."""

    env: str = "tmaze_5"
    """Environment ID."""
    memories: tuple[str, ...] = ("gru",)
    """Memory agents to compare (gru, trxl)."""
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
    unroll: int | None = None
    """Unroll factor of the time loops (default: 1 on CPU, 4 on accelerators)."""
    quiet: bool = False
    """No progress output."""


@dataclasses.dataclass(frozen=True)
class Envs:
    """List the registered environments with their observabilities and categories."""


def _error(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


def run_train(cmd: Train) -> None:
    from pobax.agent import train

    cfg = TrainConfig(**{f.name: getattr(cmd, f.name) for f in dataclasses.fields(TrainConfig)})
    result = train(cfg, cmd.out, progress=not cmd.quiet)
    print(f"run directory: {result.run_dir}")
    print(f"throughput: {result.steps_per_s:,.0f} env steps/s (all runs), compile ≈ {result.compile_s:.1f} s")
    print("final returns (last 10% of updates; mean [95% CI] over seeds):")
    sets = result.summary["sets"]
    swept = [k for k in NUMERIC if len({s[k] for s in sets}) > 1] or ["lr", "lambda0"]
    for s in sets:
        hp = ", ".join(f"{k}={s[k]:g}" for k in swept)
        d, u, a = s["disc_return"], s["return"], s["disc_return_auc"]
        print(f"  set {s['hp_index']} ({hp}): discounted {d['mean']:.3f} [{d['ci_low']:.3f}, {d['ci_high']:.3f}]"
              f"  undiscounted {u['mean']:.3f} [{u['ci_low']:.3f}, {u['ci_high']:.3f}]  AUC {a['mean']:.3f}")
    if len(sets) > 1:
        b = sets[result.summary["best_by_auc"]]
        print(f"best by AUC of the discounted return: set {b['hp_index']} ("
              + ", ".join(f"{k}={b[k]:g}" for k in swept) + ")")


def run_gap(cmd: Gap) -> None:
    from pobax.eval import format_gap, gap_report

    overrides = dict(total_steps=cmd.total_steps, num_seeds=cmd.num_seeds)
    if cmd.hidden_size is not None:
        overrides["hidden_size"] = cmd.hidden_size
    if cmd.num_envs is not None:
        overrides["num_envs"] = cmd.num_envs
    if cmd.unroll is not None:
        overrides["unroll"] = cmd.unroll
    report = gap_report(cmd.env, memories=cmd.memories, overrides=overrides, out=cmd.out, progress=not cmd.quiet,
                        sweep=cmd.sweep, sweep_seeds=cmd.sweep_seeds)
    print(format_gap(report))


def run_envs(cmd: Envs) -> None:
    from pobax.env._registry import _FAMILIES

    for f in _FAMILIES:
        ids = ", ".join(f.registered)
        print(f"{f.template:32s} observabilities: {', '.join(f.observabilities):32s} paper IDs: {ids}")
        print(f"{'':32s} categories: {', '.join(f.categories)}")


def main(argv: list[str] | None = None) -> None:
    from pobax.agent import ConfigError
    from pobax.eval import RunDirExistsError

    cmd = tyro.extras.subcommand_cli_from_dict(
        {"train": Train, "gap": Gap, "envs": Envs}, args=argv, description=__doc__
    )
    try:
        if isinstance(cmd, Train):
            run_train(cmd)
        elif isinstance(cmd, Gap):
            run_gap(cmd)
        else:
            run_envs(cmd)
    except (ConfigError, RunDirExistsError, FileNotFoundError) as e:
        _error(str(e))
    except ValueError as e:  # unknown environment, bad observability, bad environment parameter
        _error(str(e))


def entrypoint() -> None:
    main()


if __name__ == "__main__":
    main()
