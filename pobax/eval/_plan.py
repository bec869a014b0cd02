"""The plan of a benchmark: its environments, its (environment, agent) entries with their configurations and run
directories, and the plan as printed before anything trains (`pobax benchmark --dry-run`)."""

import dataclasses
import json
from pathlib import Path

from ..agent import config_from_dict, validate
from ..agent._config import make_env
from ._bounds import check_user_memory
from ..env import SUITES, spec
from ._files import CheckpointError
from ._locks import is_transient
from ..agent._network import check_overrides_read
from ._gap import AGENTS, agent_config, check_discrepancy_loss, gap_agents
from ._protocol import (EXTRA_CEILING, PART_ENV_STEPS, PROTOCOLS, env_steps, protocol_agents, protocol_config,
                        smoke_settings, sweep_grid, sweep_parts)
from ._records import check_part_config, check_part_summary, records_by_path
from ._results import RunDir

#: The order in which an environment's agents are trained.
TRAIN_ORDER = ("floor", "ceiling", "gru", "ld", "trxl")


class BenchmarkError(ValueError):
    """A benchmark that cannot run as asked (unknown suite, budget or environment; an output directory that holds
    something else)."""


def resolve_envs(envs: tuple[str, ...] = (), suite: str | None = None,
                 protocol: str = "registry") -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The environments of `suite` or the list `envs` (one of the two), each checked against the registry, and
    those of `suite` left out: under the paper's protocol a suite holds only the environments the paper
    benchmarks (`SUITES["paper"]`; e.g. maze 03, which the paper's appendix leaves out for its difficulty, has no
    tuned settings of the paper to sweep around). `envs` named one by one are all kept."""
    if bool(envs) == (suite is not None):
        raise BenchmarkError("Give either --suite (" + "|".join(SUITES) + ") or --envs ID [ID ...], not both or none.")
    if suite is not None and suite not in SUITES:
        raise BenchmarkError(f"Unknown suite {suite!r}; choose among {', '.join(SUITES)}.")
    names = SUITES[suite] if suite is not None else tuple(dict.fromkeys(envs))
    for name in names:
        spec(name)  # raises UnknownEnvironmentError with the closest name
    if suite is None or protocol != "paper":
        return names, ()
    return tuple(n for n in names if n in SUITES["paper"]), tuple(n for n in names if n not in SUITES["paper"])


@dataclasses.dataclass(frozen=True)
class Entry:
    """One (environment, agent) of a benchmark, with its training configuration."""

    env: str
    agent: object  # `pobax.eval._gap.Agent`
    config: object  # `pobax.agent.TrainConfig`: the agent's, or under the paper's protocol its sweep's
    protocol: str = "registry"
    evaluation_seeds: int = 0  # under the paper's protocol: the selected set's rerun
    part_steps: int | None = PART_ENV_STEPS  # under the paper's protocol: the most env steps of a sweep's program

    @property
    def env_steps(self) -> int:
        return env_steps(self.config) + env_steps(self.config, self.evaluation_seeds)

    @property
    def trained_at(self) -> tuple[int, int]:
        """(steps per run, seeds) of the agent's record: under the paper's protocol its evaluation's seeds."""
        return self.config.total_steps, self.evaluation_seeds if self.protocol == "paper" else self.config.num_seeds

    @property
    def grid(self) -> dict[str, tuple]:
        """Under the paper's protocol: the axes swept and their values (the paper's grid, as overridden)."""
        return {k: tuple(getattr(self.config, k)) for k in sweep_grid(self.env, self.agent)}

    def parts(self) -> list[tuple[str, object]]:
        """Under the paper's protocol: the sweep's programs (`sweep_parts`); none otherwise."""
        return sweep_parts(self.config, self.grid, self.part_steps) if self.protocol == "paper" else []


def benchmark_plan(envs: tuple[str, ...], budget: str, agents: tuple[str, ...] = AGENTS,
                   memories: tuple[str, ...] = (), overrides: dict | None = None,
                   protocol: str = "registry", part_steps: int | None = PART_ENV_STEPS) -> list[Entry]:
    """Every (environment, agent) of the benchmark with its configuration. `registry`: the agent's preset, the
    budget's steps and seeds (`spec(env).budget`), then `overrides`. `paper`: the sweep of the paper's protocol
    (`protocol_config`), its number of evaluation seeds, and the most env steps of one of its programs
    (`part_steps`, None: the sweep in one program). Every configuration is validated here, before anything
    trains."""
    if protocol not in PROTOCOLS:
        raise BenchmarkError(f"Unknown protocol {protocol!r}; choose among {', '.join(PROTOCOLS)}.")
    if part_steps is not None and part_steps < 1:
        raise BenchmarkError(f"--part-steps must be at least 1, got {part_steps}.")
    plan, built = [], set()

    def check_env_options(cfg) -> None:  # each environment built with the options before anything trains (once),
        user = ":" in cfg.memory          # and each cell of the user's checked on its environment
        if user or (cfg.env_options and (cfg.env, cfg.observability) not in built):
            env = make_env(cfg)
            built.add((cfg.env, cfg.observability))
            if user:
                check_user_memory(cfg, env)

    for env in envs:
        try:
            settings = {**spec(env).budget(budget), **(overrides or {})}
        except ValueError as e:
            raise BenchmarkError(str(e)) from None
        if protocol == "paper":
            for agent in protocol_agents(env, agents, memories):
                cfg, evaluation = protocol_config(env, agent, budget, overrides)
                validate(cfg)
                check_env_options(cfg)
                plan.append(Entry(env, agent, cfg, "paper", evaluation, part_steps))
            continue
        for agent in gap_agents(env, agents, memories):
            if budget == "smoke":
                settings = {**smoke_settings(env, agent.observability, agent.encoder), **(overrides or {})}
            cfg = agent_config(env, agent, overrides=settings)
            validate(cfg)
            check_env_options(cfg)
            check_discrepancy_loss(agent, cfg)
            plan.append(Entry(env, agent, cfg))
    check_overrides_read([(e.agent.name, e.config) for e in plan], overrides, BenchmarkError)
    return plan


def continue_splits(out: Path, plan: list[Entry]) -> list[Entry]:
    """`plan` with each protocol sweep split as its finished parts in `out` were: a sweep begun at another
    `--part-steps` continues from its finished parts instead of training the grid again under other part names.
    Tries the sizes of the finished parts; a sweep whose finished parts no such split reproduces is refused."""
    out_plan = []
    for e in plan:
        sweep = out / "runs" / e.env / f"{e.agent.name}-sweep"
        finished = {p.name: p for p in sweep.glob("*") if (p / "summary.json").is_file()} if sweep.is_dir() else {}
        names = lambda steps: {n for n, _ in sweep_parts(e.config, e.grid, steps)}  # noqa: E731
        if e.protocol != "paper" or not finished or set(finished) <= names(e.part_steps):
            out_plan.append(e)
            continue
        try:
            for p in finished.values():
                check_part_config(p)
            sizes = sorted({env_steps(config_from_dict(RunDir(p).read_config()["config"],
                                                       source=repr(str(p / "config.json"))))
                            for p in finished.values()}, reverse=True)
        except ValueError as err:  # (CheckpointError too) a damaged part, named
            raise BenchmarkError(str(err).splitlines()[0]) from None
        steps = next((n for n in sizes if set(finished) <= names(n)), None)
        if steps is None:
            raise BenchmarkError(f"{sweep} holds finished parts ({', '.join(sorted(finished))}) that no split of the "
                                 f"sweep reproduces; move them away to train the sweep anew.")
        print(f"{e.env} {e.agent.name}: continuing its sweep's split, parts of at most {steps:,} env steps "
              f"(--part-steps {steps}), from its {len(finished)} finished parts", flush=True)
        out_plan.append(dataclasses.replace(e, part_steps=steps))
    return out_plan


def run_dirs(out: Path, e: Entry) -> list[tuple[Path, object]]:
    """The run directories of an entry and their configurations, the first trained first: its run; under the paper's
    protocol its sweep's parts, then the evaluation (its configuration None: chosen by the sweep)."""
    run = out / "runs" / e.env / e.agent.name
    if e.protocol != "paper":
        return [(run, e.config)]
    return [(run.with_name(f"{e.agent.name}-sweep") / name, cfg) for name, cfg in e.parts()] + [(run, None)]


def format_plan(plan: list[Entry], todo: list[Entry], budget: str, out: Path) -> str:
    lines = [f"benchmark, budget {budget!r}, into {out}: {len(plan)} agents, {len(plan) - len(todo)} already finished",
             f"{'environment':26s} {'agent':34s} {'steps':>12s} {'seeds':>6s} {'env steps':>15s}  state"]
    seconds, unmeasured = 0.0, 0
    rates = [_left(out, e) for e in plan]  # (env steps left, rate)
    to_train = 0
    for e, (left, rate) in zip(plan, rates):
        state = "to train" if e in todo else "finished"
        dirs = run_dirs(out, e)
        parts = [run for run, _ in dirs[:-1]] if e.protocol == "paper" else []
        done, chunks = _chunks_done(dirs[0][0]) if e in todo and not parts else (0, 0)
        state = f"to resume ({done} of {chunks} chunks done)" if done else state
        to_train += left if e in todo else 0
        if e in todo and parts:
            state += f" (sweep: {sum((r / 'summary.json').exists() for r in parts)} of {len(parts)} programs done"
            if rate is None:  # borrowed from an agent of this environment with the same memory and network sizes
                like = next(((o, r) for o, (_, r) in zip(plan, rates)
                             if r and o.env == e.env and _sized_alike(o.config, e.config)), None)
                if like is None:
                    unmeasured += 1
                else:
                    rate = like[1]
                    state += f"; ~{left / rate / 60:.0f} GPU min left at {like[0].agent.name}'s rate"
            else:
                state += f"; {left / rate / 60:.0f} GPU min left"
            seconds += left / rate if rate else 0.0
            state += ")"
        lines.append(f"{e.env:26s} {e.agent.label[:34]:34s} {e.config.total_steps:>12,d} {e.config.num_seeds:>6d} "
                     f"{e.env_steps:>15,d}  {state}")
    lines.append(f"env steps left to train: {to_train:,} (of {sum(e.env_steps for e in plan):,} in the plan)")
    if seconds:
        lines.append(f"GPU time left, at the rate of each agent's finished sweep parts, or (~) of a finished agent's "
                     f"with the same memory and sizes (wall time, compile included, one GPU each): "
                     f"{seconds / 3600:.1f} h" + (f", and {unmeasured} agents not yet measured" if unmeasured else ""))
    return "\n".join(lines)


def _sized_alike(a, b) -> bool:
    """Whether two configurations train networks of one kind and size (memory, hidden and embedding sizes, number of
    environments): the programs' cost per env step differs by their observations and losses alone."""
    keys = ("memory", "hidden_size", "embed_size", "num_envs", "num_steps")
    return all(getattr(a, k, None) == getattr(b, k, None) for k in keys)


def _chunks_done(run: Path) -> tuple[int, int]:
    """(chunks done, chunks) of an interrupted run, from its checked checkpoint manifest (`RunDir.manifest`); (0, 0)
    when there is none or it is damaged (the run itself then says why, by name, when it resumes)."""
    try:
        m = RunDir(run).manifest()
        done, chunks = int(m["chunks_done"]), int(m["num_chunks"])
    except (OSError, CheckpointError, KeyError, TypeError, ValueError):  # absent or damaged: counted as not started
        return 0, 0
    return (done, chunks) if 0 <= done <= chunks and chunks > 0 else (0, 0)


def _left(out: Path, e: Entry) -> tuple[int, float | None]:
    """An entry's env steps left to train (its run; under the paper's protocol its unfinished sweep parts and its
    evaluation; less the chunks an interrupted one has done) and the env steps per second of wall time of its finished
    sweep parts (None: none has)."""
    left, done, wall = 0, 0, 0.0
    for run, cfg in run_dirs(out, e):
        steps = env_steps(cfg) if cfg is not None else env_steps(e.config, e.evaluation_seeds)
        if (run / "summary.json").exists():  # finished (the evaluation's: its record is then made from it)
            summary = RunDir(run).read_summary()
            check_part_summary(summary, run / "summary.json", **({} if cfg is not None else dict(
                kind="a run's summary", fix="restore it, or move the run directory aside to train it again")))
            if cfg is not None and summary.get("wall_s"):
                done, wall = done + steps, wall + summary["wall_s"]
            continue
        finished, chunks = _chunks_done(run)
        left += steps - steps * finished // chunks if chunks else steps
    return left, (done / wall if wall else None)


def benchmark_dir(out: str | Path) -> Path:
    """`out` as a benchmark output directory: new, empty, or one that `pobax benchmark` wrote (its benchmark.json)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BenchmarkError(f"--out {str(out)!r} is a file; pass a directory.")
    # (another pobax process starting into the same new --out: its lock and temporary files, before benchmark.json)
    if out.is_dir() and not all(is_transient(p.name) for p in out.iterdir()) and not (out / "benchmark.json").exists():
        raise BenchmarkError(f"--out {str(out)!r} holds other files and no benchmark.json: pass an empty or new "
                             f"directory, or one that an earlier `pobax benchmark` wrote.")
    return out


def planned_budget(env: str, agent: str, budget: str, protocol: str) -> tuple[int, int] | None:
    """(steps per run, seeds) that `budget` gives `agent` (a record's name) of `env` with no overrides (under the
    paper's protocol, the evaluation's seeds): agents of one budget may differ (at `smoke` the mazes' ceiling trains 4×
    the steps of their floor; λ-discrepancy's protocol evaluates on as many seeds as its larger grid has runs). None
    where the registry cannot plan it (e.g. a user's cell no longer importable)."""
    agents, memories = ((agent,), ()) if agent in AGENTS else (("ceiling",), ()) if agent == EXTRA_CEILING \
        else ((), (agent,))
    try:
        plan = benchmark_plan((env,), budget, agents, memories, None, protocol, None)
    except (ValueError, ImportError):
        return None
    return next((e.trained_at for e in plan if e.agent.name == agent), None)


def record_budget(record: dict, protocol: str) -> tuple:
    """A record's (budget, (steps per run, seeds), `planned_budget` of its agent), for `one_budget`."""
    return (record["budget"], (record["total_steps"], record["num_seeds"]),
            planned_budget(record["env"], record["agent"], record["budget"], protocol))


def check_one_budget(out: Path, plan: list[Entry], budget: str) -> None:
    """Refuse a plan that would put an agent of another budget (its name, steps per run, seeds: `one_budget`) beside
    an environment's records in `out`, which are all checked (`records_by_path`): one table holds one budget per
    environment, as `--merge` keeps it."""
    protocol = plan[0].protocol if plan else "registry"
    held, budgets = {}, {}  # per environment, its records; their budgets, planned once where needed
    for path, record in records_by_path(out):
        held.setdefault(record["env"], []).append((path, record))
    for e in plan:
        if (out / "agents" / e.env / f"{e.agent.name}.json").exists() or e.env not in held:
            continue  # reused, or refused by name if of another configuration (`run_benchmark`)
        if e.env not in budgets:
            budgets[e.env] = [(path, record_budget(r, protocol)) for path, r in held[e.env]]
        want = (budget, e.trained_at, planned_budget(e.env, e.agent.name, budget, protocol))
        for path, have in budgets[e.env]:
            if not one_budget(want, have):
                raise BenchmarkError(f"{str(path)!r} holds {e.env} at {shown_budget(have)}, and {e.agent.name} would "
                                     f"train at {shown_budget(want)}: one table holds one budget per environment; "
                                     f"pass another --out.")


def other_budget(folder: Path, record: dict) -> str | None:
    """Where the records in `folder` (an environment's, `OUT/agents/ENV`) hold one of another budget than `record`
    (`one_budget`), what it is ("'PATH' is at BUDGET, this one at BUDGET"); else None. A file there that is not a
    record is passed over (the tables name what is wrong with it)."""
    protocol = record.get("protocol") or "registry"
    mine = record_budget(record, protocol)
    for other in sorted(folder.glob("*.json")):
        try:
            have = record_budget(json.loads(other.read_text()), protocol)
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not one_budget(mine, have):
            return f"{str(other)!r} is at {shown_budget(have)}, this one at {shown_budget(mine)}"
    return None


def shown_budget(b: tuple) -> str:
    return f"{b[0]} ({b[1][0]:,} steps × {b[1][1]} seeds)"


def one_budget(a: tuple, b: tuple) -> bool:
    """Whether two agents' budgets (`record_budget`) of one environment can come from one command: the same budget
    name, and for steps and for seeds either one value (an override given to both) or each its plan's (none)."""
    (name_a, got_a, plan_a), (name_b, got_b, plan_b) = a, b
    return name_a == name_b and all(
        x == y or (plan_a is not None and plan_b is not None and (x, y) == (plan_a[i], plan_b[i]))
        for i, (x, y) in enumerate(zip(got_a, got_b)))
