"""The memory-improvability gap report: floor, memory agents and ceiling on one environment.

- floor: a memoryless agent on the `partial` observation;
- memory agents: GRU (and any other requested memory) on the `partial` observation, previous action appended;
- ceiling: the paper's ceiling agent (`spec.ceiling_memory`: a memoryless MLP, or a GRU for RockSample,
  Walker-V and HalfCheetah-V as in the paper) on the most informative observability the environment has
  (`spec.ceiling_observability`: `full`, else `perfect_memory`; RockSample's is `perfect_memory` as in the
  paper), through `spec.ceiling_encoder` (the paper's encoders, except the DMLab mazes' flattened map), plus
  the environment's programmatic reference values where it has them
  (Battleship's probability-search policy, the mazes' shortest-path oracle, T-Maze's optimum).

Each agent uses the best hyperparameters the registry has for the environment (`spec.best`: the paper's tables,
with the few deviations documented where they are registered, e.g. the HalfCheetah-V ceiling), and the
environment's recommended general settings.
"""

import dataclasses
import datetime
from pathlib import Path

from ..env import spec
from ._plots import discounted_references, plot_learning_curves
from ._results import RunDir, write_json
from ._sweep import rerun_config


class GapConfigMismatchError(ValueError):
    pass


def _train_or_reuse(cfg, path: Path, progress: bool):
    """Train one agent into `path`, or pick up what a previous (interrupted) gap report left there: a finished
    run is reused, a checkpointed one is resumed, anything else is kept aside under a new name."""
    from ..agent import train  # noqa: PLC0415 (pobax.agent imports pobax.eval)
    from ..agent._config import config_differences  # noqa: PLC0415

    if (path / "config.json").exists():
        diff = config_differences(RunDir(path).read_config().get("config", {}), cfg)
        if diff:
            raise GapConfigMismatchError(
                f"{str(path)!r} holds a run with another configuration (differs in: {', '.join(diff)}); "
                f"pass another --out for this report."
            )
        if (path / "summary.json").exists():
            if progress:
                print(f"   reusing the finished run in {path}", flush=True)
            rd = RunDir(path)
            return rd.metrics(), rd.read_summary(), path
        if (path / "checkpoint.json").exists():
            if progress:
                print(f"   resuming the interrupted run in {path}", flush=True)
            r = train(cfg, path, progress=progress, resume=True)
            return r.metrics, r.summary, r.run_dir
    if path.exists() and any(path.iterdir()):
        aside = path.with_name(f"{path.name}.incomplete-{datetime.datetime.now():%Y%m%d-%H%M%S}")
        path.rename(aside)
        if progress:
            print(f"   kept an unusable earlier run aside as {aside}", flush=True)
    r = train(cfg, path, progress=progress)
    return r.metrics, r.summary, r.run_dir


@dataclasses.dataclass(frozen=True)
class Agent:
    label: str
    observability: str
    memory: str
    encoder: str = "auto"


def gap_agents(env: str, memories: tuple[str, ...] = ("gru",)) -> list[Agent]:
    s = spec(env)
    ceiling_obs = s.ceiling_observability
    agents = [Agent("floor (memoryless, partial)", "partial", "memoryless")]
    agents += [Agent(f"{m} (partial)", "partial", m) for m in memories]
    if s.ceiling_memory is not None:  # else the ceiling is the programmatic reference only
        enc = "" if s.ceiling_encoder == "auto" else f", {s.ceiling_encoder}"
        agents.append(Agent(f"ceiling ({s.ceiling_memory}, {ceiling_obs}{enc})", ceiling_obs, s.ceiling_memory,
                            s.ceiling_encoder))
    return agents


def agent_slug(agent: Agent) -> str:
    """The agent's short name: its run directory under the report and its name for `only`."""
    return agent.label.split(" ")[0] if agent.label.startswith(("floor", "ceiling")) else agent.memory


def agent_config(env: str, agent: Agent, base=None, overrides: dict | None = None):
    """The `TrainConfig` of one gap-report agent: the paper's preset for it (`paper_preset`: the best-table row
    `memoryless`/`gru`/`trxl`, or `full` for the ceiling), then explicit overrides."""
    from ..agent import TrainConfig, apply_preset, paper_preset  # noqa: PLC0415 (pobax.agent imports pobax.eval)
    from ..agent._config import config_values  # noqa: PLC0415

    base = TrainConfig() if base is None else base
    cfg = dataclasses.replace(base, env=env, observability=agent.observability, memory=agent.memory,
                              encoder=agent.encoder)
    cfg = apply_preset(cfg, paper_preset(env, agent.memory, agent.observability))
    return apply_preset(cfg, config_values(overrides or {}))


#: The paper's sweep for T-Maze, RockSample, Battleship and masked MuJoCo (appendix, non-λ-discrepancy table).
PAPER_GRID = {"lr": (2.5e-3, 2.5e-4, 2.5e-5, 2.5e-6), "lambda0": (0.1, 0.3, 0.5, 0.7, 0.9, 0.95)}


def gap_report(
    env: str,
    *,
    memories: tuple[str, ...] = ("gru",),
    base=None,
    overrides: dict | None = None,
    out: str | Path | None = None,
    progress: bool = True,
    sweep: bool = False,
    sweep_seeds: int = 5,
    grid: dict | None = None,
    only: tuple[str, ...] | None = None,
) -> dict:
    """Train floor, memory agents and ceiling; write each run, a table and a figure under `out`.

    With `sweep=True` this is the paper's protocol: for each agent, the grid (default `PAPER_GRID`) is trained
    with `sweep_seeds` seeds in one compiled program, the set with the highest area under the discounted
    learning curve is selected, and that set is re-run with fresh seeds (the configuration's `num_seeds`).
    Without it, the paper's published best hyperparameters are used.

    Running it again with the same `out` continues an interrupted report: finished agents are reused,
    checkpointed ones resumed. `only` (e.g. `("floor",)`; names `floor`, the memories, `ceiling`) trains just
    those agents and reports them: several processes (or GPUs) can then share one `out`, and a last call
    without `only` assembles the whole report from their finished runs.
    """
    if out is None:
        out = Path("runs") / f"gap-{env}-{datetime.datetime.now():%Y%m%d-%H%M%S}"
    out = Path(out)
    agents = [(agent_slug(a), a) for a in gap_agents(env, memories)]
    if only is not None:
        unknown = sorted(set(only) - {slug for slug, _ in agents})
        if unknown:
            raise ValueError(f"gap report for {env} has no agent {', '.join(map(repr, unknown))}; choose among "
                             f"{', '.join(slug for slug, _ in agents)}.")
        agents = [(slug, a) for slug, a in agents if slug in only]
    results, curves = [], {}
    for slug, agent in agents:
        cfg = agent_config(env, agent, base, overrides or {})
        selected = None
        if sweep:
            g = grid or PAPER_GRID
            scfg = dataclasses.replace(cfg, num_seeds=sweep_seeds, **{k: tuple(v) for k, v in g.items()})
            if progress:
                print(f"== {agent.label}: sweep {len(scfg.grid())} sets × {sweep_seeds} seeds", flush=True)
            _, sweep_summary, _ = _train_or_reuse(scfg, out / f"{slug}-sweep", progress)
            best = sweep_summary["sets"][sweep_summary["best_by_auc"]]
            selected = {k: best[k] for k in g}
            cfg = rerun_config(cfg, selected)  # fresh seeds: selection and evaluation must not share them
        if progress:
            print(f"== {agent.label}: lr={cfg.lr} lambda0={cfg.lambda0} steps={cfg.total_steps:,} "
                  f"seeds={cfg.num_seeds}", flush=True)
        metrics, summary, run_dir = _train_or_reuse(cfg, out / slug, progress)
        s = summary["sets"][0]
        results.append({"agent": agent.label, "run_dir": str(run_dir), "selected_by_auc": selected,
                        "lr": cfg.lr[0], "lambda0": cfg.lambda0[0], "return": s["return"],
                        "disc_return": s["disc_return"], "steps_per_s": summary["steps_per_s"],
                        "compile_s": summary["compile_s"]})
        curves[agent.label] = metrics
    reference = spec(env).reference("partial")
    report = {"env": env, "agents": results, "reference": reference}
    fig = plot_learning_curves(curves, out / "gap.png", title=f"{env}: memory-improvability gap",
                               hlines=discounted_references(reference))
    report["figure"] = str(fig)
    write_json(out / "gap.json", report)
    return report


def format_gap(report: dict) -> str:
    """The gap report as a text table."""
    lines = [f"Memory-improvability gap on {report['env']} (final returns, mean [95% CI] over seeds)",
             f"{'agent':38s} {'discounted':>26s} {'undiscounted':>26s}  hyperparameters"]
    for a in report["agents"]:
        d, u = a["disc_return"], a["return"]
        how = "selected by AUC" if a.get("selected_by_auc") else "spec.best"
        lines.append(f"{a['agent']:38s} {d['mean']:8.3f} [{d['ci_low']:7.3f}, {d['ci_high']:7.3f}] "
                     f"{u['mean']:8.3f} [{u['ci_low']:7.3f}, {u['ci_high']:7.3f}]  "
                     f"lr={a['lr']:g} lambda0={a['lambda0']:g} ({how})")
    for k, v in report["reference"].items():
        lines.append(f"reference: {k.replace('_', ' ')} = {v:.4f}")
    lines.append(f"figure: {report['figure']}")
    return "\n".join(lines)
