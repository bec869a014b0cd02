"""The memory-improvability gap report: floor, memory agents and ceiling on one environment.

The benchmark's five agents (`AGENTS`), each at the environment's preset (`pobax.agent.paper_preset`: the paper's
recommended settings and best hyperparameters, with the registry's documented deviations):

- `floor`: a memoryless agent on the `partial` observation;
- `gru`, `ld` (λ-discrepancy: the GRU with two critics), `trxl`: memory agents on `partial`;
- `ceiling`: the family's ceiling agent (`spec.ceiling_memory`: a memoryless MLP, or a GRU where the paper used one
  or where the MLP trailed the memory agents: halfcheetah_pixels, docs/deviations.md)
  on the most informative observability it uses (`spec.ceiling_observability`), through `spec.ceiling_encoder`;

plus any extra memory (`memories`: a memory of the zoo such as `lstm`, or a user's cell `package.module:ClassName`;
its preset is the GRU's unless the registry has one for it), and the environment's programmatic reference values
where it has them (T-Maze's optimum, Battleship's probability-search policy, the mazes' shortest-path oracle, the
random policy of Battleship and the mazes).

The gap holds (`gap_verdict`) when the floor is below the best memory agent and below the ceiling, each with
disjoint 95% CIs, no memory agent's mean is above the ceiling's upper CI bound, and the ceiling's CI is above the
random policy's return where that is known.
"""

import dataclasses
import datetime
from collections.abc import Callable
from pathlib import Path

from .._distributed import single_process
from ..agent import Chunk, TrainConfig, apply_preset, make_env, paper_preset, validate
from ..agent._config import config_values
from ..agent._network import check_overrides_read, unread_fields
from ..env import PAPER_GRID, PAPER_LD_GRID, spec
from ._args import as_path, check_bools, is_count
from ._bounds import check_fits, check_user_memory
from ._plots import discounted_references, plot_learning_curves
from ._files import OUT_MARKERS, claim_out, config_fields_differing, read_json, write_json
from ._records import check_part_summary
from ._results import RunDir
from ._run import train_or_reuse
from ._stats import MIN_SEEDS_FOR_VERDICT, format_ci
from ._sweep import rerun_config

#: The benchmark's agents, in the order of the paper's figure legend.
AGENTS = ("floor", "gru", "ld", "trxl", "ceiling")


@dataclasses.dataclass(frozen=True)
class Agent:
    """One agent of a gap report: `name` is its short name (floor, gru, ld, trxl, ceiling, or an extra memory's),
    also its run directory under the report."""

    name: str
    label: str
    observability: str
    memory: str
    double_critic: bool = False
    encoder: str = "auto"


def gap_agents(env: str, agents: tuple[str, ...] = AGENTS, memories: tuple[str, ...] = ()) -> list[Agent]:
    """The agents of `env`'s gap report: those of `agents` (names in `AGENTS`), then the extra `memories` (memory
    names) before the ceiling. Raises ValueError for an unknown name."""
    if isinstance(agents, str) or isinstance(memories, str):
        raise ValueError(f"agents and memories are tuples of names (e.g. agents=('floor', 'gru')), got "
                         f"{agents if isinstance(agents, str) else memories!r}.")
    unknown = [a for a in agents if a not in AGENTS]
    if unknown:
        raise ValueError(f"Unknown agent {unknown[0]!r}; the agents are {', '.join(AGENTS)} (extra memory agents "
                         f"with --memories).")
    if not agents and not memories:
        raise ValueError(f"--agents needs at least one agent (of {', '.join(AGENTS)}), or --memories a memory.")
    s = spec(env)
    out = []
    if "floor" in agents:
        out.append(Agent("floor", "floor (memoryless, partial)", "partial", "memoryless"))
    if "gru" in agents:
        out.append(Agent("gru", "gru (partial)", "partial", "gru"))
    if "ld" in agents:
        out.append(Agent("ld", "ld (gru + λ-discrepancy, partial)", "partial", "gru", double_critic=True))
    if "trxl" in agents:
        out.append(Agent("trxl", "trxl (partial)", "partial", "trxl"))
    named = {a.name for a in out}  # a memory named twice, or as an agent too, is trained once (as --envs are)
    out += [Agent(m, f"{m} (partial)", "partial", m) for m in dict.fromkeys(memories) if m not in named]
    if "ceiling" in agents and s.ceiling_memory is not None:
        obs = s.ceiling_observability
        enc = "" if s.ceiling_encoder == "auto" else f", {s.ceiling_encoder}"
        out.append(Agent("ceiling", f"ceiling ({s.ceiling_memory}, {obs}{enc})", obs, s.ceiling_memory,
                         encoder=s.ceiling_encoder))
    return out


#: The fields that make an agent what it is (`Agent`), which overrides may not change.
IDENTITY = ("memory", "observability", "double_critic", "encoder")


def base_overrides(env: str, base) -> dict:
    """The fields of `base` (a TrainConfig, or None) that differ from TrainConfig's defaults, as overrides of every
    agent's preset: what a caller set in it wins over the registry's, as an explicit command-line flag does. Its
    `env`, where set, must be the report's."""
    from ..agent._config import ConfigError

    if base is None:
        return {}
    if not isinstance(base, TrainConfig):
        raise ConfigError(f"base must be a TrainConfig or None, got a {type(base).__name__}: pass "
                          f"TrainConfig(...), or the fields as overrides={{...}}.")
    default = TrainConfig()
    if base.env not in (default.env, env):
        raise ConfigError(f"base.env {base.env!r} is not the report's environment {env!r}: the environment is "
                          f"gap_report's first argument.")
    return {f.name: getattr(base, f.name) for f in dataclasses.fields(TrainConfig)
            if f.name != "env" and getattr(base, f.name) != getattr(default, f.name)}


def agent_config(env: str, agent: Agent, base=None, overrides: dict | None = None):
    """The `TrainConfig` of one agent: the registry's preset for it (`paper_preset`), then the fields `base` sets
    (those that differ from TrainConfig's defaults: `base_overrides`), then explicit overrides."""
    from ..agent._config import FIELDS, ConfigError

    overrides = {**base_overrides(env, base), **(overrides or {})}
    unknown = sorted(set(overrides or {}) - FIELDS)
    if unknown:  # (a typo such as total_step trained the preset's budget, silently)
        raise ConfigError(f"overrides: {', '.join(map(repr, unknown))} is not a TrainConfig field; the fields are "
                          f"TrainConfig's (e.g. total_steps, num_seeds, lr).")
    identity = sorted(k for k in set(overrides or {}) & set(IDENTITY) if overrides[k] != getattr(agent, k))
    if identity:  # what makes the floor a floor and the ceiling a ceiling: the agent's, never an override's
        raise ValueError(f"{', '.join(identity)} is set per agent by the gap report ({agent.name}: "
                         f"{', '.join(f'{k}={getattr(agent, k)}' for k in identity)}); choose agents with agents= "
                         f"and memories=, not overrides (or base).")
    cfg = dataclasses.replace(TrainConfig(), env=env, observability=agent.observability, memory=agent.memory,
                              encoder=agent.encoder, double_critic=agent.double_critic)
    cfg = apply_preset(cfg, paper_preset(env, agent.memory, agent.observability, agent.double_critic))
    return apply_preset(cfg, config_values(overrides or {}))


def check_discrepancy_loss(agent: Agent, cfg) -> None:
    """Refuse a λ-discrepancy agent whose every set has β (`ld_weight`) 0: it would be a GRU with two critics and no
    discrepancy loss, reported as λ-discrepancy (an environment without the registry's setting for it)."""
    if agent.double_critic and max(cfg.ld_weight) <= 0:
        raise ValueError(f"{cfg.env} has no λ-discrepancy setting in the registry: its '{agent.name}' agent would "
                         f"train with --ld-weight 0, a GRU with two critics and no discrepancy loss. Pass "
                         f"--ld-weight (the paper sweeps 0.25 and 0.5) and --lambda1, or leave the agent out.")


def random_return(reference: dict, metric: str) -> float | None:
    """The uniformly random policy's return on `metric`'s scale ("disc_return" or "return"), where the environment's
    reference values have it (`random_policy_discounted_return`; `random_policy_undiscounted_return`, or
    `random_policy_return` where γ = 1 makes the two one)."""
    if metric == "disc_return":
        value = reference.get("random_policy_discounted_return")
    else:
        value = reference.get("random_policy_undiscounted_return", reference.get("random_policy_return"))
    return None if value is None else float(value)


def _seeds(result: dict) -> int:
    """The number of seeds behind a final return: `n`, else the length of `per_seed`; a reference value (no seeds,
    e.g. Battleship's probability-search policy over thousands of episodes) counts as enough."""
    if result.get("n") is not None:
        return int(result["n"])
    per_seed = result.get("per_seed")
    return MIN_SEEDS_FOR_VERDICT if per_seed is None else sum(v == v for v in per_seed if v is not None)


def gap_verdict(results: dict[str, dict], random: float | None = None) -> dict:
    """Whether the gap holds for final returns `results` (agent name -> {mean, ci_low, ci_high}; every name but
    `floor` and `ceiling` is a memory agent): the floor below the best memory agent and below the ceiling with
    disjoint 95% CIs, no memory agent's mean above the ceiling's upper bound, and, where the uniformly random
    policy's return `random` is known, the ceiling's CI above it (a ceiling at the random level has learned nothing).
    Not judged (None) when the floor, the best memory agent or the ceiling has fewer than `MIN_SEEDS_FOR_VERDICT`
    seeds (`n` or `per_seed` of its result). Returns {"holds": True, False or None (cannot tell: an agent is missing), "best_memory": name, "reasons": [why
    not, ...]}."""
    known = lambda r: r is not None and r.get("mean") is not None and r["mean"] == r["mean"]  # noqa: E731 (NaN: no episode)
    results = {k: v for k, v in results.items() if known(v)}
    memory = [name for name in results if name not in ("floor", "ceiling")]
    floor, ceiling = results.get("floor"), results.get("ceiling")
    if floor is None or ceiling is None or not memory:
        return {"holds": None, "reasons": ["needs final returns of the floor, a memory agent and the ceiling"]}
    best = max(memory, key=lambda m: results[m]["mean"])
    few = [name for name in ("floor", best, "ceiling") if _seeds(results[name]) < MIN_SEEDS_FOR_VERDICT]
    if few:
        return {"holds": None, "best_memory": best,
                "reasons": [f"fewer than {MIN_SEEDS_FOR_VERDICT} seeds in the agents the verdict compares: "
                            f"{', '.join(n if n != best else f'{n} (the best memory agent)' for n in few)}"]}
    reasons = []
    if not floor["ci_high"] < results[best]["ci_low"]:
        reasons.append(f"floor's CI reaches the best memory agent's ({best})")
    if random is not None and ceiling["ci_low"] <= random:
        reasons.append(f"the ceiling at the uniformly random policy's return ({random:.3g}): it has learned nothing")
    elif ceiling["ci_high"] < floor["ci_low"]:
        reasons.append("the ceiling below the floor, not learned yet: more steps or other settings")
    elif not floor["ci_high"] < ceiling["ci_low"]:
        reasons.append("floor's CI reaches the ceiling's")
    above = [m for m in memory if results[m]["mean"] > ceiling["ci_high"]]
    if above:
        reasons.append(f"{', '.join(above)} above the ceiling")
    return {"holds": not reasons, "best_memory": best, "reasons": reasons}


def _grid(agent: Agent, grid: dict | None) -> dict:
    return grid or (PAPER_LD_GRID if agent.double_critic else PAPER_GRID)


def gap_report(
    env: str,
    *,
    agents: tuple[str, ...] = AGENTS,
    memories: tuple[str, ...] = (),
    base=None,
    overrides: dict | None = None,
    out: str | Path | None = None,
    progress: bool = True,
    sweep: bool = False,
    sweep_seeds: int = 5,
    grid: dict | None = None,
    devices: list | None = None,
    on_chunk: Callable[[Chunk], None] | None = None,
) -> dict:
    """Train the agents of the gap report; write each run, a table (`gap.json`) and a figure (`gap.png`) under `out`.

    `agents` (names in `AGENTS`) and extra `memories` choose who is trained: several processes (or GPUs) can share
    one `out` with different agents. The report holds them and every agent an earlier call reported in `out` whose
    run is finished and trained with this call's `overrides` (a call for a subset adds to the report, never shrinks
    it). Running it again with the same `out` continues an interrupted report: finished agents are reused,
    checkpointed ones resumed.

    With `sweep=True` this is the paper's protocol: for each agent, the grid (`grid`, default `PAPER_GRID`, or
    `PAPER_LD_GRID` for λ-discrepancy) is trained with `sweep_seeds` seeds in one compiled program, the set with the
    highest area under the discounted learning curve is selected, and re-run with fresh seeds (`num_seeds`).
    Without it, the registry's preset is used. `devices`, `on_chunk` (called with every chunk of every agent
    trained): as `train`'s.

    Each agent's configuration is the registry's preset for it, then the fields of `base` (a TrainConfig) that differ
    from TrainConfig's defaults (e.g. TrainConfig(total_steps=2048, hidden_size=8): those win over the preset, as
    explicit command-line flags do), then `overrides` (a dict of TrainConfig fields, winning over both). What makes
    an agent what it is (memory, observability, double_critic, encoder) is the agent's, never base's or overrides'.
    `out` (default: runs/gap-ENV-TIMESTAMP) may start with `~`; arguments of the wrong kind are refused (ConfigError,
    a ValueError) before anything is trained.
    """
    from ..agent._config import ConfigError

    single_process("gap")
    check_bools("gap_report", ConfigError, progress=progress, sweep=sweep)
    if not is_count(sweep_seeds):
        raise ConfigError(f"--sweep-seeds must be a positive integer, got {sweep_seeds!r}.")
    if out is None:
        out = Path("runs") / f"gap-{env}-{datetime.datetime.now():%Y%m%d-%H%M%S}"
    out = as_path("gap_report", "out", out, ConfigError, what="a directory path")
    chosen = gap_agents(env, agents, memories)
    overrides = {**base_overrides(env, base), **(overrides or {})}  # (the report's budget: `_earlier_agents`)
    configs, sweeps = {}, {}  # each agent's configuration, and (with `sweep`) its sweep's program
    for agent in chosen:  # every agent's configuration is checked (e.g. a --memories cell imports) before anything runs
        configs[agent.name] = cfg = agent_config(env, agent, None, overrides)
        validate(cfg)
        check_user_memory(cfg, make_env(cfg))  # its environment builds, a cell of the user's returns what it must
        check_fits(cfg, devices)
        if sweep:  # its sweep too (the re-run of the selected set is `cfg`'s size)
            try:
                sweeps[agent.name] = scfg = dataclasses.replace(
                    cfg, num_seeds=sweep_seeds, **{k: tuple(v) for k, v in _grid(agent, grid).items()})
                validate(scfg)
                check_fits(scfg, devices)
            except ValueError as e:
                raise type(e)(f"--sweep-seeds {sweep_seeds:,}: {e}") from None
        else:  # a sweep brings its own β values
            check_discrepancy_loss(agent, cfg)
    check_overrides_read(list(configs.items()), overrides, ConfigError)
    claim_out(out, OUT_MARKERS["gap"], {"command": "gap", "env": env})
    s = spec(env)
    metric = s.paper_metric
    results, curves, finals = [], {}, {}
    for agent in chosen:
        cfg = configs[agent.name]
        selected = None
        if sweep:
            g = _grid(agent, grid)
            scfg = sweeps[agent.name]
            if progress:
                print(f"== {agent.label}: sweep {len(scfg.grid())} sets × {sweep_seeds} seeds", flush=True)
            _, sweep_summary, _ = train_or_reuse(scfg, out / f"{agent.name}-sweep", progress, devices,
                                                 on_chunk)
            best = sweep_summary["sets"][sweep_summary["best_by_auc"]]
            selected = {k: best[k] for k in g}
            cfg = rerun_config(cfg, selected)  # fresh seeds: selection and evaluation must not share them
        if progress:
            print(f"== {agent.label}: lr={cfg.lr} lambda0={cfg.lambda0} steps={cfg.total_steps:,} "
                  f"seeds={cfg.num_seeds}", flush=True)
        metrics, summary, run_dir = train_or_reuse(cfg, out / agent.name, progress, devices, on_chunk)
        row = summary["sets"][0]
        results.append(_entry(agent, run_dir, selected, cfg.num_seeds, cfg.lr[0], cfg.lambda0[0], summary, row))
        curves[_curve_label(agent.label, row, cfg.num_seeds)] = metrics  # like the statistics: diverged runs left out
        finals[agent.name] = row[metric]
    for entry, metrics, row in _earlier_agents(out, env, metric, [a.name for a in chosen], overrides):
        results.append(entry)
        curves[_curve_label(entry["agent"], row, entry.get("num_seeds"))] = metrics
        finals[entry["name"]] = row[metric]
    order = {name: i for i, name in enumerate(AGENTS)}  # `gap_agents`' order: extra memories before the ceiling
    results.sort(key=lambda r: order.get(r["name"], order["ceiling"] - 0.5))
    reference = s.reference("partial")
    report = {"env": env, "metric": metric, "agents": results, "reference": reference,
              "gap": gap_verdict(finals, random_return(reference, metric))}
    hlines = discounted_references(reference) if metric == "disc_return" else {
        k.replace("_", " "): v for k, v in reference.items() if k.endswith("return") and "discounted" not in k}
    fig = plot_learning_curves(curves, out / "gap.png", column=metric, title=f"{env}: memory-improvability gap",
                               hlines=hlines, agent_colors=True)
    report["figure"] = str(fig)
    write_json(out / "gap.json", report)
    return report


def _curve_label(label: str, row: dict, num_seeds) -> str:
    """An agent's label in the gap figure, naming the seeds that diverged (left out of its curve and statistics)."""
    return label + (f" [{row['diverged']} of {num_seeds} seeds diverged, left out]" if row.get("diverged") else "")


def _earlier_agents(out: Path, env: str, metric: str, names: list[str],
                    overrides: dict) -> list[tuple[dict, object, dict]]:
    """The agents an earlier call reported in `out`'s gap.json that this call does not train (another process's
    `--agents`, or an earlier call with more of them), with their finished runs' curves and best rows: a report of
    a subset keeps them (where gap.json is missing or damaged, the agents whose run directories `out` holds). Left
    out: an entry whose run directory no longer reads as a finished run, or whose run was trained with other
    values of the fields this call sets that its agent reads (`overrides`: one report, one budget; `--num-heads`
    for a trxl does not part a floor from it), or is not the agent its name says
    (another agent's run under that name). What the report says of a kept agent is its run's, not the entry's as
    gap.json holds it (edited or damaged)."""
    try:
        earlier = read_json(out / "gap.json")
        entries = earlier["agents"] if earlier["env"] == env and earlier["metric"] == metric else []
    except (OSError, ValueError, KeyError, TypeError):
        entries = None
    if not isinstance(entries, list):  # gap.json missing or damaged: the agents' run directories are what says
        entries = [{"name": p.name} for p in sorted(out.iterdir()) if p.is_dir()] if out.is_dir() else []
    kept = []
    for entry in entries:
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or name in names or Path(name).name != name or name in (".", ".."):
            continue
        agent = _named_agent(env, name)
        if agent is None:  # no agent of this environment's report has that name
            continue
        try:
            rd = RunDir(out / name)
            summary = rd.read_summary()
            check_part_summary(summary, rd.path / "summary.json", kind="a run's summary", fix="restore it")
            saved = rd.read_config()["config"]
            unread = unread_fields(saved, overrides)
            read = {k: v for k, v in overrides.items() if k not in unread}  # the fields its agent reads
            if config_fields_differing({k: saved.get(k) for k in read}, read):
                continue
            if saved.get("env") != env or any(saved.get(k) != getattr(agent, k) for k in IDENTITY) \
                    or len(summary["sets"]) != 1:  # another agent's run (or a sweep's) under the name
                continue
            # what the report says of it is its run's (config.json, summary.json), not the entry's as it stands
            selected = entry.get("selected_by_auc")
            if not (isinstance(selected, dict) and selected and all(
                    isinstance(saved.get(k), list) and saved[k] == [v] for k, v in selected.items())):
                selected = None
            row = summary["sets"][0]
            kept.append((_entry(agent, rd.path, selected, int(saved["num_seeds"]), saved["lr"][0],
                                saved["lambda0"][0], summary, row), rd.metrics(), row))
        except (OSError, ValueError, KeyError, TypeError, IndexError):
            continue
    return kept


def _entry(agent: Agent, run_dir, selected: dict | None, num_seeds: int, lr: float, lambda0: float, summary: dict,
           row: dict) -> dict:
    """An agent's entry of the report (gap.json's "agents"), from its run's configuration, summary and best row."""
    return {"name": agent.name, "agent": agent.label, "run_dir": str(run_dir), "selected_by_auc": selected,
            "diverged": row.get("diverged", 0), "num_seeds": num_seeds, "lr": lr, "lambda0": lambda0,
            "return": row["return"], "disc_return": row["disc_return"], "steps_per_s": summary["steps_per_s"],
            "compile_s": summary["compile_s"]}


def _named_agent(env: str, name: str) -> Agent | None:
    """The agent of `env`'s report named `name` (one of `AGENTS`, else an extra memory's), or None."""
    try:
        agents = gap_agents(env, (name,)) if name in AGENTS else gap_agents(env, (), (name,))
    except ValueError:
        return None
    return agents[0] if agents else None


def format_gap(report: dict) -> str:
    """The gap report as a text table."""
    lines = [f"Memory-improvability gap on {report['env']} (final returns, mean [95% CI] over seeds)",
             f"{'agent':38s} {'discounted':>26s} {'undiscounted':>26s}  hyperparameters"]
    for a in report["agents"]:
        d, u = a["disc_return"], a["return"]
        how = "selected by AUC" if a.get("selected_by_auc") else "preset"
        diverged = f"  {a['diverged']} of {a['num_seeds']} seeds diverged (left out)" if a.get("diverged") else ""
        lines.append(f"{a['agent']:38s} {format_ci(d, '.3f', 8)} {format_ci(u, '.3f', 8)}  "
                     f"lr={a['lr']:g} lambda0={a['lambda0']:g} ({how}){diverged}")
    for k, v in report["reference"].items():
        lines.append(f"reference: {k.replace('_', ' ')} = {v:.4f}")
    gap = report["gap"]
    scale = "discounted" if report["metric"] == "disc_return" else "undiscounted"
    verdict = {True: "holds", False: "does not hold", None: "not judged"}[gap["holds"]]
    lines.append(f"gap ({scale}): {verdict}" + (f" ({'; '.join(gap['reasons'])})" if gap["reasons"] else ""))
    lines.append(f"figure: {report['figure']}")
    return "\n".join(lines)
