"""The benchmark: the gap report's agents on a list of environments at a named budget, as one results table.

An output directory `out` holds:

    benchmark.csv        one row per (environment, agent): final returns with 95% CIs, provenance, the paper's value
    benchmark.md         the same as a readable table, the paper's values beside ours, and whether each gap holds
                         (and per-episode metrics, e.g. Craftax's achievement success rates, where the env has them)
    benchmark.png        one panel per environment: learning curves with 95% CI bands, reference lines
    benchmark.json       the budget and environments asked for, and every call that wrote here
    agents/ENV/NAME.json one finished agent: its configuration, final returns per seed (and final per-episode
                         metrics), a learning curve binned to `CURVE_POINTS` points, throughput, device, JAX version
                         and commit (written once)
    runs/ENV/NAME/       the agent's run directory (checkpoints while it trains; the full metrics)

The three result files are made from `agents/` alone, so a results directory can be shipped without `runs/`.
A second call with the same `out` skips finished agents and resumes interrupted ones from their checkpoints; a
finished agent's record never changes.
"""

import dataclasses
import datetime
import math
from pathlib import Path

import jax

from .._distributed import single_process
from ..agent import config_differences, enable_compile_cache, validate
from ..env import SUITES, make, spec
from ._gap import AGENTS, agent_config, check_discrepancy_loss, gap_agents, gap_verdict, random_return
from ._parallel import Job, default_jobs, holds_gpu_memory, run_side_by_side, slot_environment
from ._plots import agent_color, curve_with_ci, discounted_references, plot_band
from ._results import RunDir, atomic_write_text, read_json, writable_dir, write_json
from ._run import ConfigMismatchError, train_or_reuse

#: The columns of `benchmark.csv`, in order.
CSV_COLUMNS = ("env", "agent", "observability", "memory", "double_critic", "budget", "total_steps", "num_seeds",
               "disc_mean", "disc_ci_low", "disc_ci_high", "undisc_mean", "undisc_ci_low", "undisc_ci_high",
               "auc_mean", "env_steps_per_s", "device", "jax_version", "pobax_commit", "paper_value")
#: The order in which an environment's agents are trained.
TRAIN_ORDER = ("floor", "ceiling", "gru", "ld", "trxl")
#: Points of the learning curve kept in an agent's record (bins of updates, averaged per seed first).
CURVE_POINTS = 100


class BenchmarkError(ValueError):
    """A benchmark that cannot run as asked (unknown suite, budget or environment; an output directory that holds
    something else)."""


class BenchmarkFailed(RuntimeError):
    """Agents trained side by side that failed (the others' records are written)."""


def resolve_envs(envs: tuple[str, ...] = (), suite: str | None = None) -> tuple[str, ...]:
    """The environments of `suite` or the list `envs` (one of the two), each checked against the registry."""
    if bool(envs) == (suite is not None):
        raise BenchmarkError("Give either --suite (" + "|".join(SUITES) + ") or --envs ID [ID ...], not both or none.")
    if suite is not None and suite not in SUITES:
        raise BenchmarkError(f"Unknown suite {suite!r}; choose among {', '.join(SUITES)}.")
    names = SUITES[suite] if suite is not None else tuple(dict.fromkeys(envs))
    for name in names:
        spec(name)  # raises UnknownEnvironmentError with the closest name
    return names


@dataclasses.dataclass(frozen=True)
class Entry:
    """One (environment, agent) of a benchmark, with its training configuration."""

    env: str
    agent: object  # `pobax.eval._gap.Agent`
    config: object  # `pobax.agent.TrainConfig`

    @property
    def env_steps(self) -> int:
        return self.config.num_updates * self.config.steps_per_update * self.config.num_seeds * len(self.config.grid())


def benchmark_plan(envs: tuple[str, ...], budget: str, agents: tuple[str, ...] = AGENTS,
                   memories: tuple[str, ...] = (), overrides: dict | None = None) -> list[Entry]:
    """Every (environment, agent) of the benchmark with its configuration: the agent's preset, the budget's steps and
    seeds (`spec(env).budget`), then `overrides`. Every configuration is validated here, before anything trains."""
    plan = []
    for env in envs:
        try:
            settings = {**spec(env).budget(budget), **(overrides or {})}
        except ValueError as e:
            raise BenchmarkError(str(e)) from None
        for agent in gap_agents(env, agents, memories):
            cfg = agent_config(env, agent, overrides=settings)
            validate(cfg)
            check_discrepancy_loss(agent, cfg)
            plan.append(Entry(env, agent, cfg))
    return plan


def _finite(x):
    """JSON-safe: NaN and infinities as null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _stat(block: dict) -> dict:
    return {k: block[k] for k in ("mean", "ci_low", "ci_high", "per_seed")}


def _trained_by(summary: dict, saved: dict, key: str) -> str:
    """The device (JAX version, commit) that trained a run: every distinct one of its sessions, joined by " + "
    where a resume ran elsewhere; the run's config.json for runs from before sessions were recorded."""
    values = list(dict.fromkeys(str(s[key]) for s in summary.get("sessions", []) if key in s))
    return " + ".join(values) if values else saved.get(key, "unknown")


def agent_record(entry: Entry, budget: str, run_dir: Path, metrics, summary: dict) -> dict:
    """The record of one finished agent (see the module docstring)."""
    cfg, agent = entry.config, entry.agent
    saved = RunDir(run_dir).read_config()
    s = spec(entry.env)
    row = summary["sets"][0]
    curve = {}
    for col, key in (("disc_return", "disc"), ("return", "undisc")):
        x, mean, lo, hi = curve_with_ci(metrics, col, points=CURVE_POINTS)
        curve["env_step"] = [int(v) for v in x]
        curve[key] = {"mean": mean.tolist(), "low": lo.tolist(), "high": hi.tolist()}
    return _finite({
        "env": entry.env, "agent": agent.name, "label": agent.label, "observability": cfg.observability,
        "memory": cfg.memory, "double_critic": cfg.double_critic, "encoder": cfg.encoder, "budget": budget,
        "total_steps": cfg.total_steps, "num_seeds": cfg.num_seeds, "metric": s.paper_metric,
        "disc": _stat(row["disc_return"]), "undisc": _stat(row["return"]), "auc": _stat(row["disc_return_auc"]),
        "diverged": row.get("diverged", 0),
        "episode_metrics": {k: _stat(v) for k, v in row.get("episode_metrics", {}).items()},
        "env_steps_per_s": summary.get("steps_per_s"), "compile_s": summary.get("compile_s"),
        "wall_s": summary.get("wall_s"), "device": _trained_by(summary, saved, "device"),
        "jax_version": _trained_by(summary, saved, "jax"),
        "pobax_commit": _trained_by(summary, saved, "pobax_commit"),
        "paper_value": s.paper_figure.get(agent.name), "reference": saved.get("env_spec", {}).get("reference") or {},
        "config": dataclasses.asdict(cfg), "curve": curve, "written": datetime.datetime.now().isoformat(timespec="seconds"),
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
) -> dict:
    """Train every agent of every environment at `budget` (and `overrides`, `TrainConfig` fields for every agent)
    into `out` (see the module docstring) and write the results. Returns {"plan": [...], "rows": [...],
    "files": [...]}; with `dry_run`, only the plan.

    `devices` (default: every local device) and `jobs`, the agents trained at once: with one job, each agent's runs
    are sharded over `devices` in this process; with several, the agents train side by side, each in a process of
    its own on one device (`jobs` above the number of devices share them; its output in `runs/ENV/NAME.log`). The
    default is one job per GPU on a machine with several GPUs (a small program gains nothing from a second GPU, two
    programs gain 2×: docs/performance.md), else one job. The jobs need the GPUs' memory that this process would
    hold with JAX's default preallocation: side by side needs XLA_PYTHON_CLIENT_PREALLOCATE=false set before JAX
    starts (the command line sets it; without it the default is one job, and `jobs` > 1 is refused)."""
    single_process("benchmark")
    if jobs is not None and jobs < 1:
        raise BenchmarkError(f"--jobs must be at least 1, got {jobs}.")
    names = resolve_envs(envs, suite)
    plan = benchmark_plan(names, budget, agents, memories, overrides)
    out = _benchmark_dir(out)
    if not dry_run:
        try:
            out.mkdir(parents=True, exist_ok=True)
            writable_dir(out)
        except OSError as e:
            raise BenchmarkError(f"Cannot write --out {str(out)!r} ({e.strerror or e}); pass another directory.") \
                from None
    records = {(e.env, e.agent.name): out / "agents" / e.env / f"{e.agent.name}.json" for e in plan}
    todo = []
    for e in plan:
        path = records[(e.env, e.agent.name)]
        if path.exists():
            diff = config_differences(read_json(path)["config"], e.config)
            if diff:
                raise ConfigMismatchError(
                    f"{str(path)!r} holds {e.env} / {e.agent.name} trained with another configuration (differs in: "
                    f"{', '.join(diff)}); pass another --out for this budget.")
        else:
            run = out / "runs" / e.env / e.agent.name  # an interrupted run resumes: it must be this agent's
            if (run / "config.json").exists():
                diff = config_differences(RunDir(run).read_config().get("config", {}), e.config)
                if diff:
                    raise ConfigMismatchError(
                        f"{str(run)!r} holds a run of {e.env} / {e.agent.name} with another configuration (differs "
                        f"in: {', '.join(diff)}); move it aside, or pass another --out.")
            todo.append(e)
    # Within an environment, the floor and the ceiling first (the gap's bounds), Transformer-XL (the slowest) last.
    rank = {name: i for i, name in enumerate(TRAIN_ORDER)}
    todo.sort(key=lambda e: (names.index(e.env), rank.get(e.agent.name, len(TRAIN_ORDER) - 1)))
    if progress:
        print(_format_plan(plan, todo, budget, out), flush=True)
    if dry_run:
        return {"plan": plan, "rows": [], "files": []}

    local = list(devices) if devices is not None else jax.local_devices()
    jobs = default_jobs(local) if jobs is None else jobs
    if jobs > 1 and len(todo) > 1 and holds_gpu_memory(local):
        raise BenchmarkError(f"--jobs {jobs}: this process holds most of every GPU's memory (JAX's preallocation), "
                             f"which the jobs' processes need; set XLA_PYTHON_CLIENT_PREALLOCATE=false before JAX "
                             f"starts (the command line does), or use --jobs 1.")
    for env, obs in dict.fromkeys((e.env, e.config.observability) for e in plan):
        make(env, obs)  # an environment whose extra is missing fails here, before anything trains
    meta_path = out / "benchmark.json"
    meta = read_json(meta_path) if meta_path.exists() else {"envs": [], "calls": []}
    meta["envs"] = list(dict.fromkeys([*meta["envs"], *names]))
    meta["calls"].append({"time": datetime.datetime.now().isoformat(timespec="seconds"), "budget": budget,
                          "envs": list(names), "agents": list(agents), "memories": list(memories),
                          "command": command})
    write_json(meta_path, meta)
    files = write_results(out)
    if jobs > 1 and len(todo) > 1:
        side = [Job(f"{e.env}: {e.agent.label}", _train_entry,
                    (e, budget, str(out), records[(e.env, e.agent.name)], jax.config.jax_compilation_cache_dir),
                    out / "runs" / e.env / f"{e.agent.name}.log") for e in todo]
        failed = run_side_by_side(side, slot_environment(local, jobs), progress,
                                  on_done=lambda job: write_results(out))
        if failed:
            raise BenchmarkFailed(f"{len(failed)} of {len(todo)} agents failed ({', '.join(j.label for j in failed)}); "
                                  f"their logs: {', '.join(str(j.log) for j in failed)}. The others' results are "
                                  f"written; the same command continues.")
        return {"plan": plan, "rows": read_rows(out), "files": write_results(out)}
    for i, e in enumerate(todo):
        _train_agent(e, budget, out, records[(e.env, e.agent.name)], progress, devices, f"[{i + 1}/{len(todo)}] ")
        files = write_results(out)
    return {"plan": plan, "rows": read_rows(out), "files": files}


def _train_agent(e: Entry, budget: str, out: Path, record: Path, progress: bool, devices: list | None = None,
                 prefix: str = "") -> None:
    """Train one agent into its run directory (or reuse / resume what is there) and write its record."""
    if progress:
        print(f"== {prefix}{e.env}: {e.agent.label} — {e.config.total_steps:,} steps × {e.config.num_seeds} seeds",
              flush=True)
    metrics, summary, run_dir = train_or_reuse(e.config, out / "runs" / e.env / e.agent.name, progress, devices)
    write_json(record, agent_record(e, budget, run_dir, metrics, summary))


def _train_entry(e: Entry, budget: str, out: str, record: Path, compile_cache: str | None) -> None:
    """A side-by-side job's process: `_train_agent` on the one device it sees, its output into its log.
    `compile_cache`: the parent's persistent compilation cache directory, if it has one."""
    if compile_cache:
        enable_compile_cache(compile_cache)
    _train_agent(e, budget, Path(out), record, True, prefix=f"on {jax.devices()[0]}: ")


def _format_plan(plan: list[Entry], todo: list[Entry], budget: str, out: Path) -> str:
    lines = [f"benchmark, budget {budget!r}, into {out}: {len(plan)} agents, {len(plan) - len(todo)} already finished",
             f"{'environment':26s} {'agent':34s} {'steps':>12s} {'seeds':>6s} {'env steps':>15s}  state"]
    for e in plan:
        state = "to train" if e in todo else "finished"
        lines.append(f"{e.env:26s} {e.agent.label[:34]:34s} {e.config.total_steps:>12,d} {e.config.num_seeds:>6d} "
                     f"{e.env_steps:>15,d}  {state}")
    lines.append(f"env steps to train: {sum(e.env_steps for e in todo):,} (of {sum(e.env_steps for e in plan):,})")
    return "\n".join(lines)


def read_records(out: str | Path) -> list[dict]:
    """The finished agents' records under `out`: environments in the suites' order (then benchmark.json's), agents in
    `AGENTS`' order (extra memories before the ceiling)."""
    out = Path(out)
    meta_path = out / "benchmark.json"
    asked = read_json(meta_path)["envs"] if meta_path.exists() else []
    order = list(dict.fromkeys([*SUITES["discrete"], *SUITES["heavy"], *asked]))
    records = [read_json(p) for p in sorted((out / "agents").glob("*/*.json"))]
    env_rank = {e: i for i, e in enumerate(order)}
    agent_rank = {a: i for i, a in enumerate(AGENTS[:-1])} | {"ceiling": len(AGENTS) + 100}
    return sorted(records, key=lambda r: (env_rank.get(r["env"], len(order)), r["env"],
                                          agent_rank.get(r["agent"], len(AGENTS)), r["agent"]))


def _row(r: dict) -> dict:
    return {"env": r["env"], "agent": r["agent"], "observability": r["observability"], "memory": r["memory"],
            "double_critic": r["double_critic"], "budget": r["budget"], "total_steps": r["total_steps"],
            "num_seeds": r["num_seeds"], "disc_mean": r["disc"]["mean"], "disc_ci_low": r["disc"]["ci_low"],
            "disc_ci_high": r["disc"]["ci_high"], "undisc_mean": r["undisc"]["mean"],
            "undisc_ci_low": r["undisc"]["ci_low"], "undisc_ci_high": r["undisc"]["ci_high"],
            "auc_mean": r["auc"]["mean"], "env_steps_per_s": r["env_steps_per_s"], "device": r["device"],
            "jax_version": r["jax_version"], "pobax_commit": r["pobax_commit"], "paper_value": r["paper_value"]}


def read_rows(out: str | Path) -> list[dict]:
    return [_row(r) for r in read_records(out)]


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def references(records: list[dict]) -> dict[str, dict]:
    """Per environment, its reference values: those its first record saved when it trained, completed by the
    registry's current ones (values measured later, such as the mazes' random policy). Where the environment cannot
    be built here (its extra not installed, an ID this install does not know), the saved ones alone."""
    out: dict[str, dict] = {}
    for r in records:
        if r["env"] not in out:
            try:
                current = spec(r["env"]).reference()
            except (ImportError, ValueError, KeyError):
                current = {}
            out[r["env"]] = {**current, **(r["reference"] or {})}
    return out


def verdicts(records: list[dict], refs: dict[str, dict] | None = None) -> dict[str, dict]:
    """Per environment, `gap_verdict` on the paper's metric of its finished agents (and its random policy's return,
    where its reference values `refs`, default `references(records)`, have it)."""
    by_env: dict[str, dict] = {}
    for r in records:
        key = "disc" if r["metric"] == "disc_return" else "undisc"
        by_env.setdefault(r["env"], {})[r["agent"]] = r[key]
    refs, metric = references(records) if refs is None else refs, {r["env"]: r["metric"] for r in records}
    return {env: gap_verdict(results, random_return(refs[env], metric[env])) for env, results in by_env.items()}


def _benchmark_dir(out: str | Path) -> Path:
    """`out` as a benchmark output directory: new, empty, or one that `pobax benchmark` wrote (its benchmark.json)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BenchmarkError(f"--out {str(out)!r} is a file; pass a directory.")
    if out.is_dir() and any(out.iterdir()) and not (out / "benchmark.json").exists():
        raise BenchmarkError(f"--out {str(out)!r} holds other files and no benchmark.json: pass an empty or new "
                             f"directory, or one that an earlier `pobax benchmark` wrote.")
    return out


def merge_results(out: str | Path, sources: tuple[str | Path, ...], command: str | None = None) -> dict:
    """Copy the finished agents' records of other benchmark output directories (`sources`, e.g. brought back from
    other machines) into `out` and write the results; nothing trains. A record `out` already has is kept (a record
    never changes): a source's different record for the same agent is reported, not copied. `out`'s benchmark.json
    gains the sources' environments and calls (each marked with the directory it came from) and a call for the
    merge. Returns {"added": [...], "kept": [...], "files": [...]} (records as "ENV/NAME")."""
    out = _benchmark_dir(out)
    if not sources:
        raise BenchmarkError("--merge needs at least one benchmark output directory to merge from.")
    metas = {}
    for src in map(Path, sources):
        if src.resolve() == out.resolve():
            raise BenchmarkError(f"--merge {str(src)!r} is --out itself; pass the directories to merge from.")
        if not (src / "benchmark.json").is_file():
            raise BenchmarkError(f"--merge {str(src)!r} has no benchmark.json: pass a directory that `pobax "
                                 f"benchmark` wrote.")
        metas[src] = read_json(src / "benchmark.json")
    # (issue 55) every record is checked before anything is copied or written: pobax/eval/_records.py
    from ._records import check_record  # noqa: PLC0415
    for src in metas:
        for path in sorted((src / "agents").glob("*/*.json")):
            check_record(read_json(path), path)
    out.mkdir(parents=True, exist_ok=True)
    writable_dir(out)
    meta_path = out / "benchmark.json"
    meta = read_json(meta_path) if meta_path.exists() else {"envs": [], "calls": []}
    added, kept = [], []
    for src, src_meta in metas.items():
        for path in sorted((src / "agents").glob("*/*.json")):
            name, dst = f"{path.parent.name}/{path.stem}", out / "agents" / path.parent.name / path.name
            if dst.exists():
                if read_json(dst) != read_json(path):
                    kept.append(name)
                continue
            dst.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(dst, path.read_text())
            added.append(name)
        meta["envs"] = list(dict.fromkeys([*meta["envs"], *src_meta.get("envs", [])]))
        meta["calls"] += [dict(c, merged_from=str(src)) for c in src_meta.get("calls", [])]
    meta["calls"].append({"time": datetime.datetime.now().isoformat(timespec="seconds"), "command": command,
                          "merged": [str(s) for s in metas], "added": added})
    write_json(meta_path, meta)
    return {"added": added, "kept": kept, "files": write_results(out)}


def write_results(out: str | Path) -> list[Path]:
    """benchmark.csv, benchmark.md and benchmark.png from the records under `out`."""
    out = Path(out)
    records = read_records(out)
    rows = [_row(r) for r in records]
    csv = ",".join(CSV_COLUMNS) + "\n" + "".join(",".join(_cell(row[c]) for c in CSV_COLUMNS) + "\n" for row in rows)
    atomic_write_text(out / "benchmark.csv", csv)
    refs = references(records)  # built once: completing them builds each environment
    atomic_write_text(out / "benchmark.md", format_markdown(records, refs))
    files = [out / "benchmark.csv", out / "benchmark.md"]
    if records:
        files.append(plot_benchmark(records, out / "benchmark.png", refs))
    return files


def _ci(block: dict) -> str:
    if block["mean"] is None:
        return "—"
    return f"{block['mean']:.3g} [{block['ci_low']:.3g}, {block['ci_high']:.3g}]"


def format_markdown(records: list[dict], refs: dict[str, dict] | None = None) -> str:
    """The results as Markdown: an overview (one row per environment) and one table per environment. `refs`: the
    environments' reference values (default `references(records)`)."""
    lines = ["# pobax benchmark", "",
             "Final returns: per seed, the mean over the last 10% of updates; then mean [95% bootstrap CI] over seeds. "
             "The paper's values are read off its results figure (about ±10%). The gap holds when the floor is below "
             "the best memory agent and below the ceiling with disjoint CIs, no memory agent is above the "
             "ceiling's upper bound, and the ceiling is above the uniformly random policy's return where that is "
             "known.", ""]
    if not records:
        return "\n".join(lines + ["No agent has finished yet.", ""])
    refs_of = references(records) if refs is None else refs
    gaps = verdicts(records, refs_of)
    envs = list(dict.fromkeys(r["env"] for r in records))
    names = [a for a in AGENTS if any(r["agent"] == a for r in records)]
    names += sorted({r["agent"] for r in records} - set(AGENTS))
    lines += ["| environment | metric | budget | " + " | ".join(names) + " | gap |",
              "|---|---|---|" + "---|" * len(names) + "---|"]
    for env in envs:
        mine = {r["agent"]: r for r in records if r["env"] == env}
        first = next(iter(mine.values()))
        key = "disc" if first["metric"] == "disc_return" else "undisc"
        cells = [f"{mine[n][key]['mean']:.3g}" if n in mine and mine[n][key]["mean"] is not None else "" for n in names]
        holds = {True: "holds", False: "no", None: "incomplete"}[gaps[env]["holds"]]
        lines.append(f"| {env} | {'discounted' if key == 'disc' else 'undiscounted'} | "
                     f"{first['budget']} ({first['total_steps']:,} × {first['num_seeds']}) | " + " | ".join(cells)
                     + f" | {holds} |")
    for env in envs:
        mine = [r for r in records if r["env"] == env]
        key = "disc" if mine[0]["metric"] == "disc_return" else "undisc"
        lines += ["", f"## {env}", "",
                  f"| agent | ours ({'discounted' if key == 'disc' else 'undiscounted'}) | paper | "
                  f"{'undiscounted' if key == 'disc' else 'discounted'} | steps × seeds | env steps/s | device | commit |",
                  "|---|---|---|---|---|---|---|---|"]
        other = "undisc" if key == "disc" else "disc"
        for r in mine:
            paper = "" if r["paper_value"] is None else f"{r['paper_value']:g}"
            sps = "" if r["env_steps_per_s"] is None else f"{r['env_steps_per_s']:,.0f}"
            diverged = f" ({r['diverged']} of {r['num_seeds']} seeds diverged, left out)" if r.get("diverged") else ""
            lines.append(f"| {r['label']}{diverged} | {_ci(r[key])} | {paper} | {_ci(r[other])} | "
                         f"{r['total_steps']:,} × {r['num_seeds']} | {sps} | {r['device']} | {r['pobax_commit']} |")
        g = gaps[env]
        verdict = {True: "holds", False: "does not hold", None: "not judged yet"}[g["holds"]]
        lines += ["", f"Gap: {verdict}" + (f" ({'; '.join(g['reasons'])})." if g["reasons"] else ".")]
        lines += _episode_metrics_table(mine)
        refs = refs_of[env]
        if refs:
            lines.append("References: " + ", ".join(f"{k.replace('_', ' ')} {v:.4g}" for k, v in refs.items()
                                                   if isinstance(v, (int, float))) + ".")
    return "\n".join(lines) + "\n"


def _episode_metrics_table(records: list[dict]) -> list[str]:
    """An environment's per-episode quantities (e.g. Craftax's achievement success rates) at the end of training,
    one row per quantity that some agent reached, one column per agent; empty where the environment has none."""
    with_metrics = [r for r in records if r.get("episode_metrics")]
    if not with_metrics:
        return []
    names = list(dict.fromkeys(k for r in with_metrics for k in r["episode_metrics"]))
    cell = lambda r, k: r.get("episode_metrics", {}).get(k, {}).get("mean")  # noqa: E731
    reached = [k for k in names if any((cell(r, k) or 0) > 0 for r in with_metrics)]
    lines = ["", f"Per-episode metrics at the end of training (mean over seeds of the last 10% of updates), the "
             f"{len(reached)} of {len(names)} that some agent reached:", "",
             "| metric | " + " | ".join(r["agent"] for r in with_metrics) + " |",
             "|---|" + "---|" * len(with_metrics)]
    for k in reached:
        lines.append(f"| {k} | " + " | ".join("" if cell(r, k) is None else f"{cell(r, k):.3f}" for r in with_metrics)
                     + " |")
    return lines


def split_references(lines: dict[str, float], low: float, high: float) -> tuple[dict, dict]:
    """Reference lines to draw on a panel whose curves span `low`…`high`, and those to name in a note instead: more
    than the curves' span above them (Battleship's full-information 87 and oracle 57.8 over curves below 25), where
    a line would squeeze the curves into the panel's bottom."""
    far = {k: y for k, y in lines.items() if y > high + (high - low)}
    return {k: y for k, y in lines.items() if k not in far}, far


def plot_benchmark(records: list[dict], path: str | Path, refs: dict[str, dict] | None = None) -> Path:
    """One panel per environment: each agent's learning curve (the paper's metric) with its 95% CI band, and the
    environment's reference lines (`refs`, default `references(records)`)."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    envs = list(dict.fromkeys(r["env"] for r in records))
    refs_of = references(records) if refs is None else refs
    cols = min(4, len(envs))
    rows = math.ceil(len(envs) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.3 * rows), squeeze=False)
    for ax, env in zip(axes.flat, envs):
        mine = [r for r in records if r["env"] == env]
        key = "disc" if mine[0]["metric"] == "disc_return" else "undisc"
        for r in mine:
            c = r["curve"]
            plot_band(ax, c["env_step"], *(c[key][k] for k in ("mean", "low", "high")), label=r["agent"],
                      color=agent_color(r["agent"]), alpha=0.2, lw=1.3)
        refs = refs_of[env]
        lines = discounted_references(refs) if key == "disc" else {
            k.replace("_", " "): v for k, v in refs.items() if k.endswith("return") and "discounted" not in k}
        near, far = split_references(lines, *ax.get_ylim())
        for label, y in near.items():
            ax.axhline(y, ls="--", lw=0.8, color="black", alpha=0.6)
            ax.annotate(label, (0.01, y), xycoords=("axes fraction", "data"), va="bottom", fontsize=6)
        if far:
            ax.annotate("above: " + ", ".join(f"{k} {v:.3g}" for k, v in far.items()), (0.01, 0.98),
                        xycoords="axes fraction", va="top", fontsize=6)
        ax.set_title(f"{env} ({mine[0]['budget']})", fontsize=9)
        ax.set_xlabel("environment steps", fontsize=8)
        ax.set_ylabel("discounted return" if key == "disc" else "return", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="lower right")
    for ax in list(axes.flat)[len(envs):]:
        ax.set_visible(False)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
