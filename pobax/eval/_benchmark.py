"""The benchmark: the gap report's agents on a list of environments at a named budget, as one results table.

An output directory `out` holds:

    benchmark.csv        one row per (environment, agent): final returns with 95% CIs, provenance, the paper's value
    benchmark.md         the same as a readable table, the paper's values beside ours, and whether each gap holds
                         (and per-episode metrics, e.g. Craftax's achievement success rates, where the env has them)
    benchmark.png        one panel per environment: learning curves with 95% CI bands, reference lines
    benchmark.json       the protocol, budget and environments asked for, and every call that wrote here
    .benchmark.lock      locked while a process updates benchmark.json or the tables (`shared_files`): processes
                         training other agents into one `out` at once keep every call and row
    agents/ENV/NAME.json one finished agent: its configuration, final returns per seed (and final per-episode
                         metrics), a learning curve binned to `CURVE_POINTS` points, throughput, device, JAX version
                         and commit (written once); under the paper's protocol also its selection (the grid, the
                         seeds, every set's AUC and final return, the selected set) and evaluation seeds
    agents/ENV/NAME.sweep.csv  under the paper's protocol: the agent's sweep table
    runs/ENV/NAME/       the agent's run directory (checkpoints while it trains; the full metrics); under the paper's
                         protocol the evaluation, and runs/ENV/NAME-sweep/PART/ the sweep's programs (`sweep_parts`)

`--protocol registry` trains each agent at the registry's settings (`pobax.agent.paper_preset`); `--protocol paper`
runs the paper's protocol per agent (`pobax.eval._protocol`: sweep, select by AUC, rerun on fresh seeds). One output
directory holds one protocol. The result files are made from `agents/` alone (`pobax.eval._report`), so a results
directory can be shipped without `runs/`.
A second call with the same `out` skips finished agents and resumes interrupted ones from their checkpoints; a
finished agent's record never changes.
"""

import dataclasses
import datetime
import sys
from collections.abc import Callable
from pathlib import Path

import jax

from .._distributed import single_process
from ..agent import Chunk, config_differences, enable_compile_cache
from ..env import make, spec
from ._args import as_path, check_bools, check_names, is_count
from ._bounds import check_fits
from ._files import check_figure_path, strict_json
from ._locks import shared_files
from ._gap import AGENTS
from ._parallel import Job, default_jobs, holds_gpu_memory, run_side_by_side, slot_environment
from ._plan import (TRAIN_ORDER, BenchmarkError, Entry, benchmark_dir, benchmark_plan, check_one_budget,
                    continue_splits, format_plan, other_budget, resolve_envs, run_dirs)
from ._plots import curve_with_ci
from ._protocol import PART_ENV_STEPS, evaluation_config, join_parts, select, selection_table
from ._records import (check_part_config, check_part_summary, check_record, read_meta, read_records_in, seal_record,
                       sweep_csv)
from ._report import read_rows, write_results
from ._results import RunDir, RunDirBusyError, atomic_write_text, read_json, writable_dir, write_json
from ._run import ConfigMismatchError, check_same_config, train_or_reuse

#: Points of the learning curve kept in an agent's record (bins of updates, averaged per seed first).
CURVE_POINTS = 100


class BenchmarkFailed(RuntimeError):
    """Agents trained side by side that failed (the others' records are written)."""


def _stat(block: dict) -> dict:
    return {k: block[k] for k in ("mean", "ci_low", "ci_high", "per_seed")}


def _trained_by(summary: dict, saved: dict, key: str) -> str:
    """The device (JAX version, commit) that trained a run: every distinct one of its sessions, joined by " + "
    where a resume ran elsewhere; the run's config.json for runs from before sessions were recorded."""
    values = list(dict.fromkeys(str(s[key]) for s in summary.get("sessions", []) if key in s))
    return " + ".join(values) if values else saved.get(key, "unknown")


def agent_record(entry: Entry, budget: str, run_dir: Path, metrics, summary: dict,
                 selection: dict | None = None) -> dict:
    """The record of one finished agent (see the module docstring). `entry.config` is the configuration that trained
    `run_dir`; under the paper's protocol `selection` is its sweep: {"config", "summary", "table", "selected"}."""
    cfg, agent = entry.config, entry.agent
    saved = RunDir(run_dir).read_config()
    if selection is not None:  # the provenance of both programs: a record trained across several is marked so
        summary = dict(summary, sessions=[*selection["summary"].get("sessions", []), *summary.get("sessions", [])])
    s = spec(entry.env)
    row = summary["sets"][0]
    curve = {}
    for col, key in (("disc_return", "disc"), ("return", "undisc")):
        x, mean, lo, hi = curve_with_ci(metrics, col, points=CURVE_POINTS)
        curve["env_step"] = [int(v) for v in x]
        curve[key] = {"mean": mean.tolist(), "low": lo.tolist(), "high": hi.tolist()}
    return strict_json({  # JSON-safe: NaN and infinities as null
        "env": entry.env, "agent": agent.name, "observability": cfg.observability,
        "label": agent.label + (f" [{' '.join(cfg.env_options)}]" if cfg.env_options else ""),  # never silent
        "memory": cfg.memory, "double_critic": cfg.double_critic, "encoder": cfg.encoder, "budget": budget,
        "total_steps": cfg.total_steps, "num_seeds": cfg.num_seeds, "metric": s.paper_metric,
        "disc": _stat(row["disc_return"]), "undisc": _stat(row["return"]), "auc": _stat(row["disc_return_auc"]),
        "diverged": row.get("diverged", 0),
        "episode_metrics": {k: _stat(v) for k, v in row.get("episode_metrics", {}).items()},
        "env_steps_per_s": summary.get("steps_per_s"), "compile_s": summary.get("compile_s"),
        "wall_s": summary.get("wall_s"), "device": _trained_by(summary, saved, "device"),
        "jax_version": _trained_by(summary, saved, "jax"),
        "pobax_commit": _trained_by(summary, saved, "pobax_commit"),
        "paper_value": s.paper_figure.get(agent.name),
        "reference": (saved["env_spec"].get("reference") if isinstance(saved.get("env_spec"), dict) else None) or {},
        "config": dataclasses.asdict(cfg), "curve": curve, "written": datetime.datetime.now().isoformat(timespec="seconds"),
        "protocol": entry.protocol,
        **({} if selection is None else {"selection": {
            "config": dataclasses.asdict(selection["config"]), "seed": selection["config"].seed,
            "num_seeds": selection["config"].num_seeds, "grid": {k: list(v) for k, v in selection["grid"].items()},
            "selected": selection["selected"], "criterion": "largest mean AUC of the discounted return over the "
            "selection seeds, among sets with no diverged run", "sets": selection["table"]},
            "evaluation": {"seed": cfg.seed, "num_seeds": cfg.num_seeds}}),
    })


def run_benchmark(
    envs: tuple[str, ...] = (),
    *,
    suite: str | None = None,
    budget: str = "reduced",
    out: str | Path = "results",
    agents: tuple[str, ...] = AGENTS,
    memories: tuple[str, ...] = (),
    overrides: dict | None = None,
    progress: bool = True,
    dry_run: bool = False,
    command: str | None = None,
    devices: list | None = None,
    jobs: int | None = None,
    protocol: str = "registry",
    part_steps: int | None = PART_ENV_STEPS,
    on_chunk: Callable[[Chunk], None] | None = None,
) -> dict:
    """Train every agent of every environment at `budget` (and `overrides`, `TrainConfig` fields for every agent)
    into `out` (see the module docstring) and write the results. Returns {"plan": [...], "rows": [...],
    "files": [...]}; with `dry_run`, only the plan.

    `devices` (default: every local device) and `jobs`, the agents trained at once: with one job, each agent's runs
    are sharded over `devices` in this process; with several, the agents train side by side, each in a process of
    its own on one device (`jobs` above the number of devices share them; its output in `runs/ENV/NAME.log`). The
    default is one job per GPU on a machine with several GPUs (a small program gains nothing from a second GPU, two
    programs side by side gain: docs/performance.md, "Several devices"), else one job. The jobs need the GPUs'
    memory that this process would hold with JAX's default preallocation: side by side needs
    XLA_PYTHON_CLIENT_PREALLOCATE=false set before JAX starts (the command line sets it; without it the default is
    one job, and `jobs` > 1 is refused).

    `protocol`: "registry" (each agent at the registry's settings) or "paper" (the paper's protocol per agent: sweep,
    selection by AUC, rerun on fresh seeds; `pobax.eval._protocol`); under it a `suite` holds the paper's
    environments only (`resolve_envs`). One output directory holds one protocol. Its
    sweeps are trained in programs of at most `part_steps` env steps (`sweep_parts`; None: each in one program),
    which side-by-side jobs train at once; an agent's evaluation starts once its sweep's parts have finished.

    `on_chunk` is called with every chunk of every agent trained (as `train`'s), in this process: it trains the
    agents one after another (one job; more are refused).

    `out` may start with `~`; arguments of the wrong kind (a string for a tuple of names, a flag that is not True or
    False, jobs that are not a positive integer) are refused (BenchmarkError) before anything is planned."""
    single_process("benchmark")
    check_bools("run_benchmark", BenchmarkError, progress=progress, dry_run=dry_run)
    check_names("run_benchmark", "envs", envs, BenchmarkError)
    if jobs is not None and not is_count(jobs):
        raise BenchmarkError(f"--jobs must be at least 1 (an integer, or None: the default), got {jobs!r}.")
    out = as_path("run_benchmark", "out", out, BenchmarkError, what="a directory path")  # ("": the cwd)
    if on_chunk is not None and jobs not in (None, 1):
        raise BenchmarkError(f"on_chunk is called in this process, and --jobs {jobs} trains the agents in processes "
                             f"of their own: pass jobs=1.")
    names, left_out = resolve_envs(envs, suite, protocol)
    plan = benchmark_plan(names, budget, agents, memories, overrides, protocol, part_steps)
    out = benchmark_dir(out)
    plan = continue_splits(out, plan)
    meta_path = out / "benchmark.json"
    held = read_meta(meta_path).get("protocol", "registry") if meta_path.exists() else protocol
    if held != protocol:
        read_records_in(out)  # a record of another protocol than benchmark.json's: that file was edited, say so
        raise BenchmarkError(f"--out {str(out)!r} holds the {held!r} protocol's results; pass another --out for "
                             f"--protocol {protocol}.")
    if not dry_run:
        _check_fits(plan, devices)  # (a dry run plans for other machines too)
        check_figure_path(out / "benchmark.png", "the figure")  # (not written over at the end: refused now)
        try:
            out.mkdir(parents=True, exist_ok=True)
            writable_dir(out)
        except OSError as e:
            raise BenchmarkError(f"Cannot write --out {str(out)!r} ({e.strerror or e}); pass another directory.") \
                from None
    records = {(e.env, e.agent.name): out / "agents" / e.env / f"{e.agent.name}.json" for e in plan}
    check_one_budget(out, plan, budget)  # and every record the tables read, before anything is written
    todo = []
    for e in plan:
        path = records[(e.env, e.agent.name)]
        if path.exists():
            record = read_json(path)
            diff = config_differences(record.get("selection", {}).get("config", record["config"]), e.config)
            if e.protocol == "paper" and record.get("evaluation", {}).get("num_seeds") != e.evaluation_seeds:
                diff.append("the evaluation's seeds (--num-seeds)")
            if diff:
                raise ConfigMismatchError(
                    f"{str(path)!r} holds {e.env} / {e.agent.name} trained with another configuration (differs in: "
                    f"{', '.join(diff)}); pass another --out for this budget.")
        else:
            for run, cfg in run_dirs(out, e):  # an interrupted run resumes: it must be this agent's
                if cfg is not None and (run / "config.json").exists():  # (the evaluation's: once selected)
                    check_same_config(run, cfg, f"a run of {e.env} / {e.agent.name}",
                                      "move it aside, or pass another --out")
            todo.append(e)
    # Within an environment, the floor and the ceiling first (the gap's bounds), Transformer-XL (the slowest) last.
    rank = {name: i for i, name in enumerate(TRAIN_ORDER)}
    todo.sort(key=lambda e: (names.index(e.env), rank.get(e.agent.name, len(TRAIN_ORDER) - 1)))
    if progress:
        if left_out:
            print(f"suite {suite!r} under the paper's protocol: the paper's environments only; left out "
                  f"{', '.join(left_out)} (not in the paper's benchmark; --envs ID trains it)", flush=True)
        print(format_plan(plan, todo, budget, out), flush=True)
    if dry_run:
        return {"plan": plan, "rows": [], "files": []}

    local = list(devices) if devices is not None else jax.local_devices()
    jobs = (1 if on_chunk is not None else default_jobs(local)) if jobs is None else jobs
    side = _jobs(todo, budget, out, records)
    if jobs > 1 and len(side) > 1 and holds_gpu_memory(local):
        raise BenchmarkError(f"--jobs {jobs}: this process holds most of every GPU's memory (JAX's preallocation), "
                             f"which the jobs' processes need; set XLA_PYTHON_CLIENT_PREALLOCATE=false before JAX "
                             f"starts (the command line does), or use --jobs 1.")
    for env, obs in dict.fromkeys((e.env, e.config.observability) for e in plan):
        make(env, obs)  # an environment whose extra is missing fails here, before anything trains
    with shared_files(out):  # another process may be adding its call to the same --out
        meta = read_meta(meta_path)
        meta["protocol"] = protocol
        meta["envs"] = list(dict.fromkeys([*meta["envs"], *names]))
        meta["calls"].append({"time": datetime.datetime.now().isoformat(timespec="seconds"), "budget": budget,
                              "protocol": protocol, "envs": list(names), "agents": list(agents),
                              "memories": list(memories), "command": command})
        write_json(meta_path, meta)
    files = write_results(out)
    if jobs > 1 and len(side) > 1:
        failed = run_side_by_side(side, slot_environment(local, min(jobs, len(side))), progress,
                                  on_done=lambda job: write_results(out))
        if failed:
            raise BenchmarkFailed(f"{len(failed)} of {len(side)} jobs failed ({', '.join(j.label for j in failed)}); "
                                  f"their logs: {', '.join(str(j.log) for j in failed)}. The others' results are "
                                  f"written; the same command continues.")
        return {"plan": plan, "rows": read_rows(out), "files": write_results(out)}
    busy = []
    for i, e in enumerate(todo):
        try:
            _train_agent(e, budget, out, records[(e.env, e.agent.name)], progress, devices,
                         f"[{i + 1}/{len(todo)}] ", on_chunk)
        except RunDirBusyError as err:  # another benchmark into this --out trains it: the others go on
            busy.append(e)
            print(f"   skipped: {err}", file=sys.stderr, flush=True)
            continue
        files = write_results(out)
        # An agent's programs serve no other agent. Kept, they add up: on the CPU, the discrete suite's smoke protocol
        # (38 agents) ran out of memory mappings for LLVM's compiled code after 19 agents ("Cannot allocate memory").
        jax.clear_caches()
    if busy:  # the tables again, with the records of those the other process has finished meanwhile
        files = write_results(out)
    left = [f"{e.env} / {e.agent.name}" for e in busy if not records[(e.env, e.agent.name)].exists()]
    if left:
        raise BenchmarkFailed(f"{len(left)} of {len(todo)} agents ({', '.join(left)}) were being trained by another "
                              f"process into this --out; the others' results are written: run the same command "
                              f"again once that process has ended, for their records.")
    return {"plan": plan, "rows": read_rows(out), "files": files}


def _check_fits(plan: list[Entry], devices: list | None) -> None:
    """Every program of the plan fits in the memory of `devices` (`check_fits`: a lower bound), checked before
    anything is written or trained: an agent's, or under the paper's protocol its sweep's parts and evaluation."""
    for e in plan:
        programs = [cfg for _, cfg in e.parts()] or [e.config]
        if e.protocol == "paper":  # one set of the grid stands for the selected one
            programs.append(evaluation_config(e.config, {k: v[0] for k, v in e.grid.items()}, e.evaluation_seeds))
        for cfg in programs:
            try:
                check_fits(cfg, devices)
            except ValueError as err:
                raise BenchmarkError(f"{e.env} / {e.agent.name}: {err}") from None


def _jobs(todo: list[Entry], budget: str, out: Path, records: dict) -> list[Job]:
    """The side-by-side jobs of `todo`: an agent each; under the paper's protocol, a job per part of a sweep of
    several parts first, then the agent's (selection and evaluation) once they have finished."""
    cache = jax.config.jax_compilation_cache_dir
    jobs = []
    for e in todo:
        label, log = f"{e.env}: {e.agent.label}", out / "runs" / e.env / f"{e.agent.name}.log"
        parts = run_dirs(out, e)[:-1] if e.protocol == "paper" else []
        after = []
        if len(parts) > 1:
            for run, cfg in parts:
                if not (run / "summary.json").exists():
                    after.append(f"{label}, sweep part {run.name}")
                    jobs.append(Job(after[-1], _train_part, (cfg, str(run), cache),
                                    log.with_name(f"{e.agent.name}-sweep-{run.name}.log")))
        jobs.append(Job(label, _train_entry, (e, budget, str(out), records[(e.env, e.agent.name)], cache), log,
                        after=tuple(after)))
    return jobs


def _train_agent(e: Entry, budget: str, out: Path, record: Path, progress: bool, devices: list | None = None,
                 prefix: str = "", on_chunk: Callable[[Chunk], None] | None = None) -> None:
    """Train one agent into its run directories (or reuse / resume what is there) and write its record: under the
    paper's protocol the sweep, the selection, then the evaluation. `on_chunk`: as `train`'s."""
    if progress:
        what = f"{len(e.config.grid())} sets × " if e.protocol == "paper" else ""
        print(f"== {prefix}{e.env}: {e.agent.label} — {e.config.total_steps:,} steps × {what}{e.config.num_seeds} "
              f"seeds" + (f", then the selected set × {e.evaluation_seeds} seeds" if e.protocol == "paper" else ""),
              flush=True)
    dirs = run_dirs(out, e)
    if e.protocol != "paper":
        metrics, summary, run_dir = train_or_reuse(e.config, dirs[0][0], progress, devices, on_chunk)
        _write_record(record, agent_record(e, budget, run_dir, metrics, summary), run_dir)
        return
    grid = e.grid
    summaries = []
    for i, (run, cfg) in enumerate(dirs[:-1]):
        if progress and len(dirs) > 2:
            print(f"== {prefix}{e.env}: {e.agent.label} — sweep part {i + 1}/{len(dirs) - 1} ({run.name}): "
                  f"{len(cfg.grid())} sets × {cfg.num_seeds} seeds", flush=True)
        summaries.append(_finished_part(cfg, run, progress, grid)
                         or train_or_reuse(cfg, run, progress, devices, on_chunk)[1])
    sweep_summary = join_parts(e.config, grid, summaries)
    selected = select(sweep_summary, grid, str(dirs[0][0].parent), unfinished_ok=budget == "smoke")
    table = selection_table(sweep_summary, grid)
    ecfg = evaluation_config(e.config, selected, e.evaluation_seeds)
    if progress:
        print(f"== {prefix}{e.env}: {e.agent.label} — selected {selected}", flush=True)
    metrics, summary, run_dir = train_or_reuse(ecfg, dirs[-1][0], progress, devices, on_chunk)
    atomic_write_text(record.with_suffix(".sweep.csv"), sweep_csv(table))
    _write_record(record, agent_record(dataclasses.replace(e, config=ecfg), budget, run_dir, metrics, summary,
                                       {"config": e.config, "summary": sweep_summary, "table": table,
                                        "selected": selected, "grid": grid}), run_dir)


def _write_record(path: Path, record: dict, run_dir: Path) -> None:
    """A finished agent's record, checked (`check_record`) and written once: where another process (`--merge`, a
    benchmark) wrote this agent's record, or one of its environment at another budget, while this one trained, that
    one is kept and the user told where this one's run is."""
    check_record(record, path)
    with shared_files(path.parents[2]):
        if path.exists():
            print(f"warning: {str(path)!r} was written by another process while this one trained it; that record is "
                  f"kept, this one's run is in {str(run_dir)!r}.", file=sys.stderr, flush=True)
            return
        if conflict := other_budget(path.parent, record):
            print(f"warning: {conflict}, written by another process while this one trained {record['agent']}: one "
                  f"table holds one budget per environment, so that record is kept and this one is not written. Its "
                  f"finished run is in {str(run_dir)!r}: move the other budget's records out of --out and run this "
                  f"command again, which reads the run instead of training it.", file=sys.stderr, flush=True)
            return
        write_json(path, seal_record(record))


def _finished_part(cfg, run: Path, progress: bool, grid: dict) -> dict | None:
    """The summary of a finished part of a sweep in `run` (its configuration checked), else None. Its summary is
    all the selection reads: a part's directory copied from another machine without its metrics and model (tens of
    MB for RockSample's) is still finished."""
    if not (run / "summary.json").exists():
        return None
    check_part_config(run)
    check_same_config(run, cfg)
    summary = RunDir(run).read_summary()
    check_part_summary(summary, run / "summary.json", grid)
    if progress:
        print(f"   reusing the finished sweep part in {run}", flush=True)
    return summary


def _train_entry(e: Entry, budget: str, out: str, record: Path, compile_cache: str | None) -> None:
    """A side-by-side job's process: `_train_agent` on the one device it sees, its output into its log.
    `compile_cache`: the parent's persistent compilation cache directory, if it has one."""
    if compile_cache:
        enable_compile_cache(compile_cache)
    _train_agent(e, budget, Path(out), record, True, prefix=f"on {jax.devices()[0]}: ")


def _train_part(cfg, run: str, compile_cache: str | None) -> None:
    """A side-by-side job's process: one part of a protocol sweep (`sweep_parts`) into `run`, or what is there
    reused or resumed."""
    if compile_cache:
        enable_compile_cache(compile_cache)
    print(f"== on {jax.devices()[0]}: sweep part {run}: {len(cfg.grid())} sets × {cfg.num_seeds} seeds", flush=True)
    train_or_reuse(cfg, Path(run), True)

