"""The benchmark's results from its records: `benchmark.csv`, `benchmark.md`, `benchmark.png` (see `_benchmark`).

Intervals are recomputed from each record's per-seed finals by the rule of `pobax.eval.mean_ci` (percentile bootstrap
with at least 10 seeds, Student's t below), so that every table states one method; a gap needs 5 seeds per agent.

Records of the paper's protocol (`protocol: "paper"`) make the protocol table, and that table comes from one commit,
one device kind and one JAX version: the most common among them. A protocol record trained elsewhere, on a dirty tree
or across several commits, devices or JAX versions (a resume on another machine) is listed apart, in a labelled
table, and never judged with the others.
"""

import collections
import math
from pathlib import Path

from ..env import SUITES, spec
from ._files import check_figure_path, existing_dir, read_or_none, save_figure
from ._locks import shared_files
from ._gap import AGENTS, gap_verdict, random_return
from ._plots import agent_color, discounted_references, plot_band
from ._protocol import EXTRA_CEILING
from ._records import read_meta, read_records_in, sweep_csv
from ._results import atomic_write_text
from ._stats import format_ci, mean_ci

#: The columns of `benchmark.csv`, in order.
CSV_COLUMNS = ("env", "agent", "protocol", "observability", "memory", "double_critic", "budget", "total_steps",
               "num_seeds", "disc_mean", "disc_ci_low", "disc_ci_high", "undisc_mean", "undisc_ci_low",
               "undisc_ci_high", "ci_method", "auc_mean", "env_steps_per_s", "device", "jax_version", "pobax_commit",
               "paper_value")


def _restat(block: dict) -> dict:
    """A record's statistic with its interval recomputed from its per-seed values (`mean_ci`)."""
    per_seed = block.get("per_seed")
    if not per_seed:
        return block
    return {**block, **mean_ci([math.nan if v is None else v for v in per_seed])}


def read_records(out: str | Path) -> list[dict]:
    """The finished agents' records under `out`: environments in the suites' order (then benchmark.json's), agents in
    `AGENTS`' order (extra memories before the ceiling)."""
    out = existing_dir(out, "a `pobax benchmark --out` directory")
    asked = read_meta(out / "benchmark.json")["envs"]
    order = list(dict.fromkeys([*SUITES["discrete"], *SUITES["heavy"], *asked]))
    records = read_records_in(out)
    for r in records:
        r.setdefault("protocol", "registry")
        for key in ("disc", "undisc", "auc"):
            r[key] = _restat(r[key])
    env_rank = {e: i for i, e in enumerate(order)}
    agent_rank = {a: i for i, a in enumerate(AGENTS[:-1])} | {"ceiling": len(AGENTS) + 100,
                                                               EXTRA_CEILING: len(AGENTS) + 101}
    return sorted(records, key=lambda r: (env_rank.get(r["env"], len(order)), r["env"],
                                          agent_rank.get(r["agent"], len(AGENTS)), r["agent"]))


def _row(r: dict) -> dict:
    return {"env": r["env"], "agent": r["agent"], "protocol": r.get("protocol", "registry"), "observability": r["observability"],
            "memory": r["memory"],
            "double_critic": r["double_critic"], "budget": r["budget"], "total_steps": r["total_steps"],
            "num_seeds": r["num_seeds"], "disc_mean": r["disc"]["mean"], "disc_ci_low": r["disc"]["ci_low"],
            "disc_ci_high": r["disc"]["ci_high"], "undisc_mean": r["undisc"]["mean"],
            "undisc_ci_low": r["undisc"]["ci_low"], "undisc_ci_high": r["undisc"]["ci_high"],
            "ci_method": r[_key(r)].get("ci_method"), "auc_mean": r["auc"]["mean"], "env_steps_per_s": r["env_steps_per_s"], "device": r["device"],
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
            out[r["env"]] = {**current, **(r.get("reference") or {})}
    return out


def _key(r: dict) -> str:
    """The record's block on the paper's metric: "disc" or "undisc"."""
    return "disc" if r["metric"] == "disc_return" else "undisc"


def reference_ceiling(env: str, refs: dict) -> dict | None:
    """The paper's ceiling of `env` where it is a programmatic policy's value (`spec(env).protocol()`), as a final
    return {mean, ci_low, ci_high} from the reference values `refs`; None where it is an agent or not measured."""
    try:
        ceiling = spec(env).protocol()["ceiling"]
    except (ValueError, KeyError):
        return None
    key = ceiling.get("reference")
    if key is None or refs.get(key) is None:
        return None
    prefix = key.removesuffix("mean_return")
    return {"mean": refs[key], "ci_low": refs.get(f"{prefix}ci95_low", refs[key]),
            "ci_high": refs.get(f"{prefix}ci95_high", refs[key]), "reference": key}


def verdicts(records: list[dict], refs: dict[str, dict] | None = None) -> dict[str, dict]:
    """Per environment, `gap_verdict` on the paper's metric of its finished agents (and its random policy's return,
    where its reference values `refs`, default `references(records)`, have it). The extra ceiling of the paper's
    protocol (`EXTRA_CEILING`) is not one of the judged agents; where the protocol's ceiling is a reference value
    (Battleship's probability-search policy), that value is the ceiling."""
    refs = references(records) if refs is None else refs
    by_env: dict[str, dict] = {}
    for r in records:
        results = by_env.setdefault(r["env"], {})
        if r["agent"] != EXTRA_CEILING:
            results[r["agent"]] = r[_key(r)]
        if r.get("protocol") == "paper" and "ceiling" not in results:
            ref = reference_ceiling(r["env"], refs[r["env"]])
            if ref is not None:
                results["ceiling"] = ref
    metric = {r["env"]: r["metric"] for r in records}
    return {env: gap_verdict(results, random_return(refs[env], metric[env])) for env, results in by_env.items()}


def _provenance(r: dict) -> tuple[str, str, str]:
    return r["pobax_commit"], r["device"], r["jax_version"]


def protocol_table(records: list[dict]) -> tuple[list[dict], list[dict], tuple | None]:
    """The paper's protocol records of one commit, device kind and JAX version (the most common), and the others
    (another commit, device or JAX, a dirty tree, or trained across several: a resume elsewhere), with that
    provenance."""
    paper = [r for r in records if r.get("protocol", "registry") == "paper"]
    single = [r for r in paper if not any(" + " in str(v) for v in _provenance(r))
              and not str(r["pobax_commit"]).endswith("-dirty")]
    if not single:
        return [], paper, None
    main = collections.Counter(_provenance(r) for r in single).most_common(1)[0][0]
    table = [r for r in single if _provenance(r) == main]
    return table, [r for r in paper if r not in table], main


def write_results(out: str | Path) -> list[Path]:
    """benchmark.csv (every record), benchmark.md (`format_markdown`) and benchmark.png (the protocol table's curves
    where there is one, else those at the registry's settings) from the records under `out`; each protocol record's
    sweep table (`agents/ENV/NAME.sweep.csv`) written again from the record where it differs (edited or gone)."""
    out = Path(out)
    with shared_files(out):  # the records as read now, not overwritten by another process's older view
        records = read_records(out)
        rows = [_row(r) for r in records]
        csv = ",".join(CSV_COLUMNS) + "\n" + "".join(",".join(_cell(row[c]) for c in CSV_COLUMNS) + "\n"
                                                     for row in rows)
        atomic_write_text(out / "benchmark.csv", csv)
        for r in records:  # each protocol record's sweep table, from the (checked) record: an edited one rebuilt
            sets = r.get("selection", {}).get("sets")
            table, text = out / "agents" / r["env"] / f"{r['agent']}.sweep.csv", sweep_csv(sets) if sets else None
            if text is not None and read_or_none(table) != text.encode():  # (garbage, non-UTF-8 too: rebuilt)
                atomic_write_text(table, text)
        refs = references(records)  # built once: completing them builds each environment
        atomic_write_text(out / "benchmark.md", format_markdown(records, refs))
        files = [out / "benchmark.csv", out / "benchmark.md"]
        plotted = protocol_table(records)[0] or [r for r in records if r.get("protocol", "registry") != "paper"]
        if plotted:
            files.append(plot_benchmark(plotted, out / "benchmark.png", refs))
    return files


def _ci(block: dict) -> str:
    if block["mean"] is None:
        return "—"
    return format_ci(block, ".3g")


METHOD = ("Final returns: per seed, the mean over the last 10% of updates; then the mean over seeds [95% interval: "
          "percentile bootstrap with 10 seeds or more, Student's t below, none (nan) for one seed; a gap is not judged "
          "with fewer than 5 seeds per agent]. The paper's values are read off its results figure (about ±10%). The "
          "gap holds when the floor is below the best memory agent and below the ceiling with disjoint intervals, no "
          "memory agent is above the ceiling's upper bound, and the ceiling is above the uniformly random policy's "
          "return where that is known.")
PROTOCOL = ("The paper's protocol (`--protocol paper`): per agent, the paper's sweep grid with its selection seeds "
            "at the paper's fixed settings, the set with the largest mean AUC among those that never diverged, rerun "
            "on 30 evaluation seeds disjoint from the selection seeds; the numbers are the evaluation's. The ceiling "
            "is the paper's; `ceiling_pobax` is the registry's ceiling where it differs (not judged). Each "
            "agent's sweep table is `agents/ENV/NAME.sweep.csv`.")


def format_markdown(records: list[dict], refs: dict[str, dict] | None = None) -> str:
    """The results as Markdown: the paper's protocol table (one commit, device and JAX version), its records from
    elsewhere apart, then the records at the registry's settings; each an overview (one row per environment) and one
    table per environment. `refs`: the environments' reference values (default `references(records)`)."""
    lines = ["# pobax benchmark", "", METHOD, ""]
    if not records:
        return "\n".join(lines + ["No agent has finished yet.", ""])
    refs = references(records) if refs is None else refs
    table, apart, prov = protocol_table(records)
    registry = [r for r in records if r.get("protocol", "registry") != "paper"]
    if table:
        lines += ["## The paper's protocol", "", PROTOCOL, "",
                  f"Commit `{prov[0]}`, {prov[1]}, JAX {prov[2]}.", ""]
        lines += _tables(table, refs, level="###")
    if apart:
        lines += ["", "## Protocol rows outside the table", "",
                  "Trained at another commit, device or JAX version, on a dirty tree, or across several (a resume "
                  "elsewhere): not part of the protocol table.", "",
                  "| environment | agent | final | commit | device | JAX |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['env']} | {r['label']} | {_ci(r[_key(r)])} | {r['pobax_commit']} | {r['device']} | "
                  f"{r['jax_version']} |" for r in apart]
    if registry:
        if table or apart:
            lines += ["", "## At the registry's settings (`--protocol registry`)", ""]
        lines += _tables(registry, refs, level="###" if (table or apart) else "##")
    return "\n".join(lines) + "\n"


def _tables(records: list[dict], refs_of: dict[str, dict], level: str) -> list[str]:
    """An overview of `records` (one row per environment) and one table per environment."""
    gaps = verdicts(records, refs_of)
    envs = list(dict.fromkeys(r["env"] for r in records))
    names = [a for a in AGENTS if any(r["agent"] == a for r in records)]
    names += sorted({r["agent"] for r in records} - set(AGENTS))
    if "ceiling" not in names and any(reference_ceiling(e, refs_of[e]) for e in envs if
                                      any(r.get("protocol", "registry") == "paper" for r in records)):
        names.append("ceiling")
    lines = ["| environment | metric | budget | " + " | ".join(names) + " | gap |",
             "|---|---|---|" + "---|" * len(names) + "---|"]
    for env in envs:
        mine = {r["agent"]: r for r in records if r["env"] == env}
        first = next(iter(mine.values()))
        key = _key(first)
        ref = reference_ceiling(env, refs_of[env]) if first.get("protocol", "registry") == "paper" else None
        cells = []
        for n in names:
            if n in mine and mine[n][key]["mean"] is not None:
                cells.append(f"{mine[n][key]['mean']:.3g}")
            elif n == "ceiling" and ref is not None:
                cells.append(f"{ref['mean']:.3g} ({ref['reference'].removesuffix('_mean_return')})")
            else:
                cells.append("")
        holds = {True: "holds", False: "no", None: "not judged"}[gaps[env]["holds"]]
        lines.append(f"| {env} | {'discounted' if key == 'disc' else 'undiscounted'} | "
                     f"{first['budget']} ({first['total_steps']:,} × {first['num_seeds']}) | " + " | ".join(cells)
                     + f" | {holds} |")
    for env in envs:
        mine = [r for r in records if r["env"] == env]
        key = _key(mine[0])
        lines += ["", f"{level} {env}", "",
                  f"| agent | ours ({'discounted' if key == 'disc' else 'undiscounted'}) | paper | "
                  f"{'undiscounted' if key == 'disc' else 'discounted'} | steps × seeds | selected | env steps/s | "
                  f"device | commit |",
                  "|---|---|---|---|---|---|---|---|---|"]
        other = "undisc" if key == "disc" else "disc"
        for r in mine:
            paper = "" if r["paper_value"] is None else f"{r['paper_value']:g}"
            sps = "" if r["env_steps_per_s"] is None else f"{r['env_steps_per_s']:,.0f}"
            diverged = f" ({r['diverged']} of {r['num_seeds']} seeds diverged, left out)" if r.get("diverged") else ""
            chosen = r.get("selection", {}).get("selected") or {}
            chosen = ", ".join(f"{k} {v:g}" for k, v in chosen.items())
            lines.append(f"| {r['label']}{diverged} | {_ci(r[key])} | {paper} | {_ci(r[other])} | "
                         f"{r['total_steps']:,} × {r['num_seeds']} | {chosen} | {sps} | {r['device']} | "
                         f"{r['pobax_commit']} |")
        g = gaps[env]
        verdict = {True: "holds", False: "does not hold", None: "not judged"}[g["holds"]]
        lines += ["", f"Gap: {verdict}" + (f" ({'; '.join(g['reasons'])})." if g["reasons"] else ".")]
        lines += _episode_metrics_table(mine)
        refs = refs_of[env]
        if refs:
            lines.append("References: " + ", ".join(f"{k.replace('_', ' ')} {v:.4g}" for k, v in refs.items()
                                                   if isinstance(v, (int, float))) + ".")
    return lines


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
    check_figure_path(path, "the figure")
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
