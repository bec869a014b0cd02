"""The paper's protocol for one (environment, agent): sweep, select by AUC, rerun the selected set on fresh seeds.

`pobax benchmark --protocol paper` (and `gap --protocol paper`) trains each agent this way instead of at the
registry's settings (`--protocol registry`):

1. **Settings the paper fixes** are the paper's own tables as printed (`paper_preset(..., original=True)`: its
   environments per seed, hidden and embedding sizes, entropy, reward scaling), the steps of its text
   (`spec(env).protocol()["total_steps"]` at `--budget paper`; the family's `reduced` steps at `--budget reduced`).
2. **Sweep**: every set of the paper's grid for the agent (`spec(env).protocol()`: step size × λ0, and λ1 × β for
   λ-discrepancy; the mazes' own grids) with the paper's selection seeds (5; Battleship 10), in one compiled program.
3. **Selection**: the largest mean area under the discounted learning curve among the sets none of whose runs
   diverged (`summarize`'s `best_by_auc`); a sweep whose every set diverged selects nothing and is refused.
   A sweep larger than `PART_ENV_STEPS` is trained as several programs (`sweep_parts`), each a product of the
   grid's values and a run directory of its own, so that a sweep advances part by part across interrupted calls
   and side-by-side jobs train its parts at once; their tables are joined in the grid's order (`join_parts`).
4. **Evaluation**: the selected set rerun with 30 seeds whose base seed is `RERUN_SEED_OFFSET` away from the
   selection's, so that no evaluation run starts from a selection run's key (`selection_keys` /
   `evaluation_keys`, checked in the tests). The reported numbers are the evaluation's.

The ceiling is the paper's (`spec(env).protocol()["ceiling"]`): an agent (RockSample's GRU on `perfect_memory`, the
mazes' memoryless agent on the map), or a programmatic policy's value (Battleship's probability-search policy, from
the environment's reference values, not trained). Where the registry's ceiling differs from the paper's, it is
trained as well, as the extra row `EXTRA_CEILING`, labelled as pobax's and never used for the gap verdict.
"""

import dataclasses
import functools
import math

import jax
import numpy as np

from ..agent import TrainConfig, apply_preset, paper_preset
from ..agent._config import config_values
from ..agent._validate import validate
from ..agent._train import seed_keys
from ..agent._encoders import encoder_kind
from ..env import make, spec
from ..env._registry import SMOKE_BUDGET
from ._gap import Agent, gap_agents
from ._stats import best_by_auc
from ._sweep import rerun_config

#: The protocols of `pobax benchmark --protocol`.
PROTOCOLS = ("registry", "paper")
#: The agent name of the registry's ceiling where it is not the paper's (an extra row under the paper's protocol).
EXTRA_CEILING = "ceiling_pobax"
#: Seeds of a sweep at the `smoke` budget (the machinery only). Its rerun trains as many runs as the sweep (seeds of
#: the selected set), so that both are one compiled program of the same shape.
SMOKE_SEEDS = 2
#: The most env steps of one program of a protocol sweep (`sweep_parts`): T-Maze's sweeps (at most 2.7e8 env steps)
#: stay whole, RockSample's and Battleship's are split into parts of minutes on one GPU.
PART_ENV_STEPS = 300_000_000


def smoke_settings(env: str, observability: str, encoder: str) -> dict:
    """The `smoke` budget for an agent: `SMOKE_BUDGET`; where the agent's encoder is a CNN, rollouts of 16 steps
    instead of 64 (still three updates; Transformer-XL's gradient window 16), and where it is the FullImageCNN of
    a large image (a maze's map), compiled with XLA's optimisations. Unoptimised CPU convolutions over a map are
    slower by more than the compile time they save (maze 01's map ceiling's smoke sweep did not finish within 900 s
    without them; even optimised a CPU trains maze 03's map ceiling, FullImageCNN on 53×81 cells, at about 55 env
    steps/s), while the SmallImageCNN of a maze's first-person view compiles faster than it then trains slower
    (maze 01's smoke floor, 8 runs: 28-32 s in all unoptimised against 42-46 s optimised on 2 cores)."""
    settings = dict(SMOKE_BUDGET)
    kind = _encoder_kind(env, observability, encoder)
    if kind in ("small_cnn", "full_cnn"):
        settings.update(num_steps=16, total_steps=3 * SMOKE_BUDGET["num_envs"] * 16, window_grad=16)
    if kind == "full_cnn":
        settings.update(fast_compile=False)
    return settings


@functools.lru_cache(maxsize=None)
def _encoder_kind(env: str, observability: str, encoder: str) -> str:
    """The encoder `encoder` resolves to for `env`'s observations under `observability` (an environment made once
    per pair)."""
    if encoder != "auto":  # named: no environment to make
        return encoder
    return encoder_kind(getattr(make(env, observability).observation_space, "shape", ()))


def smoke_grid(grid: dict[str, tuple]) -> dict[str, tuple]:
    """A sweep grid at the `smoke` budget: each axis's first and last value (the machinery of sweep, selection and
    rerun, at a quarter of the paper's 4 × 6 sets and 16 of λ-discrepancy's 54)."""
    return {k: (v[0], v[-1]) if len(v) > 1 else tuple(v) for k, v in grid.items()}


class ProtocolError(ValueError):
    """A protocol that cannot go on as asked (a sweep whose every set diverged: nothing to select)."""


def protocol_agents(env: str, agents: tuple[str, ...], memories: tuple[str, ...] = ()) -> list[Agent]:
    """The agents of `env` under the paper's protocol: the registry's floor and memory agents, the paper's ceiling
    (not an agent where the paper's ceiling is a programmatic policy's value), and the registry's ceiling as
    `EXTRA_CEILING` where it differs from the paper's."""
    registry = gap_agents(env, agents, memories)
    out = [a for a in registry if a.name != "ceiling"]
    ceiling = spec(env).protocol()["ceiling"]
    ours = next((a for a in registry if a.name == "ceiling"), None)
    if "ceiling" in agents and "reference" not in ceiling:
        enc = "" if ceiling["encoder"] == "auto" else f", {ceiling['encoder']}"
        paper = Agent("ceiling", f"ceiling ({ceiling['memory']}, {ceiling['observability']}{enc})",
                      ceiling["observability"], ceiling["memory"], encoder=ceiling["encoder"])
        out.append(paper)
        if ours is not None and (ours.observability, ours.memory, ours.encoder) == (
                paper.observability, paper.memory, paper.encoder):
            ours = None
    if ours is not None:
        out.append(dataclasses.replace(ours, name=EXTRA_CEILING, label=f"pobax's {ours.label}, not the paper's"))
    return out


def sweep_grid(env: str, agent: Agent) -> dict[str, tuple]:
    """The paper's sweep grid for this agent on `env`."""
    p = spec(env).protocol()
    return {k: tuple(v) for k, v in (p["ld_grid"] if agent.double_critic else p["grid"]).items()}


def protocol_config(env: str, agent: Agent, budget: str, overrides: dict | None = None) -> tuple[TrainConfig, int]:
    """The sweep's configuration (the paper's fixed settings, its grid, its selection seeds, the budget's steps, then
    `overrides`, `TrainConfig` fields) and the number of evaluation seeds (`overrides["num_seeds"]` where given: the
    seeds reported; the selection's are the paper's)."""
    p = spec(env).protocol()
    cfg = dataclasses.replace(TrainConfig(), env=env, observability=agent.observability, memory=agent.memory,
                              double_critic=agent.double_critic)
    cfg = apply_preset(cfg, paper_preset(env, agent.memory, agent.observability, agent.double_critic,
                                         original=True))
    cfg = dataclasses.replace(cfg, encoder=agent.encoder)
    grid = sweep_grid(env, agent)
    if budget == "smoke":
        steps = dict(smoke_settings(env, agent.observability, agent.encoder), num_seeds=SMOKE_SEEDS)
        grid = smoke_grid(grid)
        evaluation = SMOKE_SEEDS * math.prod(len(v) for v in grid.values())
    else:
        total = p["total_steps"] if budget == "paper" else spec(env).budget(budget)["total_steps"]
        steps = dict(total_steps=total, num_seeds=p["selection_seeds"])
        evaluation = p["evaluation_seeds"]
    overrides = dict(overrides or {})
    evaluation = int(overrides.pop("num_seeds", evaluation))  # the reported seeds; the selection's are the paper's
    settings = {**steps, **grid, **overrides}
    cfg = apply_preset(cfg, config_values(settings))
    validate(dataclasses.replace(cfg, num_seeds=evaluation))  # the rerun's seeds, as --num-seeds is checked elsewhere
    return cfg, evaluation


def selection_table(summary: dict, grid: dict) -> list[dict]:
    """Every set of a sweep: its hyperparameters, mean AUC and final returns over the selection seeds, diverged
    runs."""
    return [{**{k: s[k] for k in grid}, "auc": s["disc_return_auc"]["mean"], "disc_final": s["disc_return"]["mean"],
             "undisc_final": s["return"]["mean"], "diverged": s.get("diverged", 0), "num_seeds": s.get("num_seeds")}
            for s in summary["sets"]]


def select(summary: dict, grid: dict, where: str, unfinished_ok: bool = False) -> dict:
    """The selected set's hyperparameters: the largest mean AUC among the sets with no diverged run. Where no set
    finished an episode: an error, or with `unfinished_ok` (the `smoke` budget, whose returns mean nothing) the
    grid's first set."""
    if summary.get("all_sets_diverged"):
        raise ProtocolError(f"Every set of the sweep in {where} has a diverged run: the protocol selects among sets "
                            f"that never diverged, so nothing can be selected. Inspect the sweep's metrics.")
    best = summary["sets"][summary["best_by_auc"]]
    if best["disc_return_auc"]["mean"] != best["disc_return_auc"]["mean"]:
        if unfinished_ok:
            return {k: summary["sets"][0][k] for k in grid}
        raise ProtocolError(f"No set of the sweep in {where} finished an episode: nothing to select; train longer "
                            f"(--total-steps).")
    return {k: best[k] for k in grid}


def evaluation_config(sweep_cfg: TrainConfig, selected: dict, num_seeds: int) -> TrainConfig:
    """The selected set on `num_seeds` fresh seeds (`rerun_config`)."""
    return rerun_config(sweep_cfg, selected, num_seeds)


def _keys(cfg: TrainConfig) -> set[bytes]:
    data = np.asarray(jax.random.key_data(seed_keys(np.uint32(cfg.seed % 2**32), cfg.num_seeds)))
    return {row.tobytes() for row in data.reshape(cfg.num_seeds, -1)}


def selection_keys(sweep_cfg: TrainConfig) -> set[bytes]:
    """The starting keys of the sweep's seeds (shared by all its sets)."""
    return _keys(sweep_cfg)


def evaluation_keys(eval_cfg: TrainConfig) -> set[bytes]:
    """The starting keys of the evaluation's seeds."""
    return _keys(eval_cfg)


def env_steps(cfg: TrainConfig, runs: int | None = None) -> int:
    """The env steps `cfg` trains: its whole updates × `runs` (default: every set × seed of its grid)."""
    return cfg.num_updates * cfg.steps_per_update * (cfg.num_seeds * len(cfg.grid()) if runs is None else runs)


def _split(values: tuple, parts: int) -> list[tuple]:
    """`values` in `parts` contiguous runs whose lengths differ by one at most."""
    bounds = [round(i * len(values) / parts) for i in range(parts + 1)]
    return [values[a:b] for a, b in zip(bounds, bounds[1:])]


def sweep_parts(cfg: TrainConfig, grid: dict, max_env_steps: int | None = PART_ENV_STEPS
                ) -> list[tuple[str, TrainConfig]]:
    """The sweep `cfg` (its `grid`'s axes swept) as programs of at most `max_env_steps` env steps each (None: one
    program), as (name, configuration): split along the axis with the most values (the first of the grid's order
    among equals) into as few even parts as fit, each part split again the same way while it is too large and has
    an axis left; a set's seeds are never split. Each part is a product of the grid's values, so one program; its
    name gives the values that set it apart from the whole grid (`lr=0.0025+lambda0=0.1,0.3`), "all" when whole."""
    def split(c: TrainConfig) -> list[TrainConfig]:
        steps = env_steps(c)
        axes = [k for k in grid if len(getattr(c, k)) > 1]
        if max_env_steps is None or steps <= max_env_steps or not axes:
            return [c]
        axis = max(axes, key=lambda k: len(getattr(c, k)))  # max keeps the first of equals
        values = tuple(getattr(c, axis))
        per_value = steps // len(values)
        n = min(len(values), math.ceil(len(values) / max(1, max_env_steps // per_value)))
        return [p for chunk in _split(values, n) for p in split(dataclasses.replace(c, **{axis: chunk}))]

    def name(part: TrainConfig) -> str:
        differ = [k for k in grid if tuple(getattr(part, k)) != tuple(getattr(cfg, k))]
        return "+".join(f"{k}=" + ",".join(f"{v:g}" for v in getattr(part, k)) for k in differ) or "all"

    return [(name(p), p) for p in split(cfg)]


def join_parts(cfg: TrainConfig, grid: dict, summaries: list[dict]) -> dict:
    """The parts' summaries (`sweep_parts`, in any order) as one summary of the whole sweep `cfg`: its sets in
    `cfg.grid()`'s order, `best_by_auc` and `all_sets_diverged` as `summarize` gives them, and every part's sessions
    (where and on which commit each trained)."""
    found = {}
    for summary in summaries:
        for s in summary["sets"]:
            found[tuple(float(s[k]) for k in grid)] = s
    sets = []
    for h, hp in enumerate(cfg.grid()):
        key = tuple(float(hp[k]) for k in grid)
        if key not in found:
            raise ProtocolError(f"The sweep's parts lack the set {dict(zip(grid, key))}.")
        sets.append({**found[key], "hp_index": h})
    best, all_diverged = best_by_auc(sets)
    return {"env": cfg.env, "num_seeds": cfg.num_seeds, "sets": sets, "best_by_auc": best,
            "all_sets_diverged": all_diverged, "diverged_runs": sum(s["diverged"] for s in sets),
            "sessions": [x for summary in summaries for x in summary.get("sessions", [])],
            "parts": len(summaries)}
