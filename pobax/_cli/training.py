"""The commands that train: train, sweep, gap and benchmark, and what they print."""

import shlex
import sys
import typing
from pathlib import Path

from .._paths import printable, shell_word
from ..agent import NUMERIC, TrainConfig
from .args import _TRAIN_FIELDS, UsageError, _check_read, _devices, _overrides, _train_config
from .commands import Benchmark, Gap, Sweep, Train


def _print_sets(summary: dict) -> None:
    from pobax.eval import format_ci

    sets = summary["sets"]
    swept = [k for k in NUMERIC if len({s[k] for s in sets}) > 1] or ["lr", "lambda0"]
    for s in sets:
        hp = ", ".join(f"{k}={s[k]:g}" for k in swept)
        d, u, a = s["disc_return"], s["return"], s["disc_return_auc"]
        diverged = f"  ({s['diverged']} of {s['num_seeds']} seeds diverged, left out)" if s.get("diverged") else ""
        print(f"  set {s['hp_index']} ({hp}): discounted {format_ci(d)}  undiscounted {format_ci(u)}  "
              f"AUC {a['mean']:.3f}{diverged}")
    if len(sets) > 1:
        b = sets[summary["best_by_auc"]]
        print(f"best by AUC of the discounted return: set {b['hp_index']} ("
              + ", ".join(f"{k}={b[k]:g}" for k in swept) + ")"
              + (" — every set has a diverged run" if summary.get("all_sets_diverged") else ""))


def run_train(cmd: Train, given: frozenset[str], on_chunk=None) -> None:
    from pobax.agent import config_from_dict
    from pobax.eval import RunDir, train
    from pobax.eval._run import check_resumable, default_out

    if cmd.resume is not None:
        flags = sorted(given | ({"preset"} if cmd.preset else set()) | ({"out"} if cmd.out else set()))
        if flags:
            raise UsageError(f"--resume continues the run with its saved configuration; drop "
                             f"{', '.join('--' + f.replace('_', '-') for f in flags)}.")
        check_resumable(cmd.resume)
        saved = RunDir(cmd.resume).read_config().get("config", {})
        cfg, out = config_from_dict(saved, source=f"{str(cmd.resume / 'config.json')!r}"), cmd.resume
    else:
        cfg = _train_config(cmd, given)
        _check_read(cfg, given)
        out = cmd.out if cmd.out is not None else default_out(cfg)
    # once the run directory is claimed
    started = None if cmd.quiet else lambda path: print(f"run directory: {printable(path)}", flush=True)
    result = train(cfg, out, progress=not cmd.quiet, resume=cmd.resume is not None, max_chunks=cmd.max_chunks,
                   loggers=cmd.log, on_start=started, on_chunk=on_chunk, devices=_devices(cmd.devices))
    import jax

    if jax.process_index() != 0:  # another process of a multi-process run: process 0 reports
        return
    print(f"run directory: {printable(result.run_dir)}")
    if not result.summary["finished"]:
        print(f"stopped after --max-chunks; continue with: pobax train --resume {shell_word(result.run_dir)}")
    if result.steps_per_s == result.steps_per_s:  # NaN after a single chunk: no steady chunk to time
        print(f"throughput: {result.steps_per_s:,.0f} env steps/s (all runs), compile ≈ {result.compile_s:.1f} s")
    print("final returns (last 10% of updates; mean [95% CI] over seeds):")
    _print_sets(result.summary)


def run_sweep(cmd: Sweep, given: frozenset[str], on_chunk=None) -> None:
    from pobax.eval import format_ci, sweep

    if cmd.resume is not None or cmd.max_chunks is not None:
        raise UsageError("sweep does not take --resume/--max-chunks: run the same sweep with the same --out to "
                         "continue it.")
    cfg, axes = _train_config(cmd, given), _parse_axes(cmd.axis)
    _check_read(cfg, given, axes)
    report = sweep(cfg, out=cmd.out, axes=axes, rerun_seeds=cmd.rerun_seeds,
                   progress=not cmd.quiet, max_runs=cmd.max_runs, devices=_devices(cmd.devices), on_chunk=on_chunk)
    print(f"sweep directory: {printable(report['out'])}")
    for p in report["programs"]:
        print(f"program {p['axis'] or '(base)'}: {printable(p['run_dir'])}")
        _print_sets(p["summary"])
    b = report["best"]
    print(f"selected by AUC: {b['axis'] or '(base)'} set {b['hp_index']} "
          + ", ".join(f"{k}={b['hyperparameters'][k]:g}" for k in NUMERIC) + f" -> preset {printable(report['preset'])}"
          + (f" (every set has a diverged run; this one {b['diverged']} of {b['num_seeds']} seeds)"
             if b.get("diverged") else ""))
    if report.get("rerun"):
        r = report["rerun"]
        print(f"re-run with {cmd.rerun_seeds} fresh seeds: discounted {format_ci(r)}")


def _parse_axes(items: tuple[str, ...]) -> dict[str, list]:
    axes = {}
    for item in items:
        key, sep, values = item.partition("=")
        if not sep or not values:
            raise UsageError(f"--axis takes KEY=V1,V2,... (e.g. hidden_size=64,128), got {item!r}.")
        if key not in _TRAIN_FIELDS or key in NUMERIC:
            hint = " (numeric hyperparameters are swept with their own flags, e.g. --lr 2.5e-3 2.5e-4)" if key in NUMERIC else ""
            raise UsageError(f"--axis {key!r} is not a structural TrainConfig field{hint}.")
        if key in axes:
            raise UsageError(f"--axis gives {key} twice; give all its values once (e.g. {key}=V1,V2).")
        axes[key] = [_axis_value(key, v) for v in values.split(",")]
    return axes


_FIELD_TYPES = typing.get_type_hints(TrainConfig)


def _axis_value(key: str, text: str):
    """One `--axis` value of the TrainConfig field `key`, read as the field's type."""
    tp = _FIELD_TYPES[key]
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if type(None) in typing.get_args(tp) and text.lower() in ("none", "null"):
        return None
    if len(args) == 1 and typing.get_origin(tp) is not tuple:  # `int | None`: the int
        tp = args[0]
    if tp is bool:
        if text.lower() in ("1", "true", "yes", "0", "false", "no"):
            return text.lower() in ("1", "true", "yes")
        raise UsageError(f"--axis {key}: {text!r} is not a boolean (true or false).")
    if typing.get_origin(tp) is typing.Literal:
        if text not in typing.get_args(tp):
            raise UsageError(f"--axis {key}: {text!r} is not one of {', '.join(typing.get_args(tp))}.")
        return text
    if tp not in (int, float, str):
        raise UsageError(f"--axis {key} takes {tp} values, which --axis cannot list; sweep it by separate runs.")
    try:
        return tp(text)
    except ValueError:
        raise UsageError(f"--axis {key}: cannot read {text!r} as {tp.__name__}.") from None


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
        print("results: " + ", ".join(printable(f) for f in result["files"]))
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
    if not cmd.merge and any(a == "--merge" or a.startswith("--merge=") for a in argv):
        raise UsageError("--merge needs the benchmark output directories to merge from: --merge DIR [DIR ...].")
    if cmd.merge:
        from pobax.eval import merge_results

        if cmd.envs or cmd.suite:
            raise UsageError("--merge trains nothing: drop --envs / --suite (the records come from the merged "
                             "directories).")
        result = merge_results(out, cmd.merge, command="pobax " + shlex.join(argv))
        for line in result["why"]:
            print(line, file=sys.stderr)
        print((out / "benchmark.md").read_text())
        n, k = len(result["added"]), len(result["parts"])
        parts = f" and {k} finished sweep part{'s' * (k != 1)} (the protocol continues from them)" if k else ""
        print(f"merged {n} record{'s' * (n != 1)}{parts} into {printable(out)}"
              + (": " + ", ".join(result["added"]) if result["added"] else ""))
        print("results: " + ", ".join(printable(f) for f in result["files"]))
        return
    overrides = _overrides(cmd, given, per_agent=("env", "memory", "observability", "double_critic", "encoder"))
    result = benchmark(cmd.envs, suite=cmd.suite, budget=cmd.budget, out=out, agents=cmd.agents,
                       memories=cmd.memories, overrides=overrides, progress=not cmd.quiet, dry_run=cmd.dry_run,
                       command="pobax " + shlex.join(argv), devices=_devices(cmd.devices), jobs=cmd.jobs,
                       protocol=cmd.protocol, on_chunk=on_chunk, **_part_steps(cmd))
    if not cmd.dry_run:
        print((out / "benchmark.md").read_text())
        print("results: " + ", ".join(printable(f) for f in result["files"]))
