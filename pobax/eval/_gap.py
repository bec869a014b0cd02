"""The memory-improvability gap report: floor, memory agents and ceiling on one environment.

- floor: a memoryless agent on the `partial` observation;
- memory agents: GRU (and any other requested memory) on the `partial` observation, previous action appended;
- ceiling: a memoryless agent on the most informative observability the environment has (`full`, else
  `perfect_memory`), plus the environment's programmatic reference values where it has them.

Each agent uses the paper's best hyperparameters for the environment when the registry has them (`spec.best`),
and the environment's recommended general settings.
"""

import dataclasses
import datetime
from pathlib import Path

from ..env import spec
from ._plots import plot_learning_curves
from ._results import write_json


@dataclasses.dataclass(frozen=True)
class Agent:
    label: str
    observability: str
    memory: str
    best_key: str  # key of the paper's best-hyperparameter table


def gap_agents(env: str, memories: tuple[str, ...] = ("gru",)) -> list[Agent]:
    s = spec(env)
    ceiling_obs = "full" if "full" in s.observabilities else "perfect_memory"
    agents = [Agent("floor (memoryless, partial)", "partial", "memoryless", "memoryless")]
    agents += [Agent(f"{m} (partial)", "partial", m, m) for m in memories]
    agents.append(Agent(f"ceiling (memoryless, {ceiling_obs})", ceiling_obs, "memoryless", "full"))
    return agents


def agent_config(env: str, agent: Agent, base=None, overrides: dict | None = None):
    """The `TrainConfig` of one gap-report agent: paper presets, then explicit overrides."""
    from ..agent import TrainConfig  # noqa: PLC0415 (pobax.agent imports pobax.eval)

    base = TrainConfig() if base is None else base
    s = spec(env)
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {}
    for k, v in {**s.recommended, **s.best.get(agent.best_key, {}), **(overrides or {})}.items():
        if k in fields:
            # numeric hyperparameters are tuples (sweepable); presets give single values
            values[k] = (v,) if isinstance(getattr(base, k), tuple) and not isinstance(v, tuple) else v
    return dataclasses.replace(base, env=env, observability=agent.observability, memory=agent.memory, **values)


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
) -> dict:
    """Train floor, memory agents and ceiling; write each run, a table and a figure under `out`.

    With `sweep=True` this is the paper's protocol: for each agent, the grid (default `PAPER_GRID`) is trained
    with `sweep_seeds` seeds in one compiled program, the set with the highest area under the discounted
    learning curve is selected, and that set is re-run with fresh seeds (the configuration's `num_seeds`).
    Without it, the paper's published best hyperparameters are used.
    """
    from ..agent import train  # noqa: PLC0415

    if out is None:
        out = Path("runs") / f"gap-{env}-{datetime.datetime.now():%Y%m%d-%H%M%S}"
    out = Path(out)
    results, curves = [], {}
    for agent in gap_agents(env, memories):
        cfg = agent_config(env, agent, base, overrides or {})
        slug = agent.label.split(" ")[0] if agent.label.startswith(("floor", "ceiling")) else agent.memory
        selected = None
        if sweep:
            g = grid or PAPER_GRID
            scfg = dataclasses.replace(cfg, num_seeds=sweep_seeds, **{k: tuple(v) for k, v in g.items()})
            if progress:
                print(f"== {agent.label}: sweep {len(scfg.grid())} sets × {sweep_seeds} seeds", flush=True)
            rs = train(scfg, out / f"{slug}-sweep", progress=progress)
            best = rs.summary["sets"][rs.summary["best_by_auc"]]
            selected = {k: best[k] for k in g}
            # fresh seeds for the re-run: selection and evaluation must not share them
            cfg = dataclasses.replace(cfg, seed=cfg.seed + 10_000, **{k: (v,) for k, v in selected.items()})
        if progress:
            print(f"== {agent.label}: lr={cfg.lr} lambda0={cfg.lambda0} steps={cfg.total_steps:,} "
                  f"seeds={cfg.num_seeds}", flush=True)
        r = train(cfg, out / slug, progress=progress)
        s = r.summary["sets"][0]
        results.append({"agent": agent.label, "run_dir": str(r.run_dir), "selected_by_auc": selected,
                        "lr": cfg.lr[0], "lambda0": cfg.lambda0[0], "return": s["return"],
                        "disc_return": s["disc_return"], "steps_per_s": r.steps_per_s, "compile_s": r.compile_s})
        curves[agent.label] = r.metrics
    reference = spec(env).reference("partial")
    report = {"env": env, "agents": results, "reference": reference}
    hlines = {k.replace("_", " "): v for k, v in reference.items() if "discounted" in k and "undiscounted" not in k}
    fig = plot_learning_curves(curves, out / "gap.png", title=f"{env}: memory-improvability gap", hlines=hlines)
    report["figure"] = str(fig)
    write_json(out / "gap.json", report)
    return report


def format_gap(report: dict) -> str:
    """The gap report as a text table."""
    lines = [f"Memory-improvability gap on {report['env']} (final returns, mean [95% CI] over seeds)",
             f"{'agent':38s} {'discounted':>26s} {'undiscounted':>26s}  hyperparameters"]
    for a in report["agents"]:
        d, u = a["disc_return"], a["return"]
        how = "selected by AUC" if a.get("selected_by_auc") else "paper's best"
        lines.append(f"{a['agent']:38s} {d['mean']:8.3f} [{d['ci_low']:7.3f}, {d['ci_high']:7.3f}] "
                     f"{u['mean']:8.3f} [{u['ci_low']:7.3f}, {u['ci_high']:7.3f}]  "
                     f"lr={a['lr']:g} lambda0={a['lambda0']:g} ({how})")
    for k, v in report["reference"].items():
        lines.append(f"reference: {k.replace('_', ' ')} = {v:.4f}")
    lines.append(f"figure: {report['figure']}")
    return "\n".join(lines)
