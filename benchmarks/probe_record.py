"""One-factor probe record: the agents of two or more `pobax benchmark --out` directories, or the runs of two or
more `pobax train --out` directories (the arms), side by side.

    python benchmarks/probe_record.py --arm mjx=runs/wv-mjx --arm positional=runs/wv-pos \
        --what "Walker-V floor and GRU, MJX vs positional" --command "pobax benchmark ..." --json probe.json

An arm given as a finished `pobax train --out` directory (its summary.json, seal checked) is read as a record of
one agent, named as the benchmark names the agent of its memory, observability, critic and encoder (else its memory),
its curve from its metrics (`metrics.csv`, or every chunk's `metrics/*.csv`: what `detached_queue.py --metrics` brings
back of a run trained under a packed directory's `runs/`); one of several hyperparameter sets trained in one program
is named by its index, `NAME=DIR#N` (the summary's `hp_index`: its hyperparameters, returns and curve). An arm given
as one record file (`OUT/agents/ENV/AGENT.json`, checked as `pobax benchmark` checks it: a row of the shipped table as
the control of a probe that retrains one factor of it) is that agent alone.

Every arm must hold records of the same environments and agents, or (`--across-agents`) one record each, of one
environment, whatever its agent (a floor beside a memory agent: the memory is then a factor). For each of them the
configurations are compared field by field: the fields that differ between arms are the probe's factors, printed and
recorded (`factors`), and a probe whose arms differ in more than one field is reported as such (exit 1 with
`--one-factor`). Per arm and agent the record keeps the final returns (undiscounted and discounted: mean, interval,
per seed), the AUC, the paper's value, the mean return at each tenth of training (from the record's curve), the
final return under the paper's definition for its MuJoCo rows (`final_by_definition`: the last point of the curve
smoothed by a Savitzky-Golay filter of window 30 and order 3, beside pobax's and the curve's last bin), throughput,
device, JAX and commit.
"""

import json
import os
import sys
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from pobax._cli.args import ScriptParser
from pobax.agent import config_from_dict
from pobax.agent._config import config_differences
from pobax.eval._benchmark import agent_record
from pobax.eval._gap import IDENTITY, Agent, gap_agents
from pobax.eval._metrics_table import ordered_metrics, read_metrics
from pobax.eval._plan import Entry
from pobax.eval._records import read_record, read_records_in
from pobax.eval._results import RunDir

TENTHS = 10
#: The paper's smoothing of its masked and pixel MuJoCo curves (its appendix): a Savitzky-Golay filter of window 30
#: and polynomial order 3, applied here to the record's curve (100 bins of updates; the paper's points are its logs').
SAVGOL_WINDOW, SAVGOL_ORDER = 30, 3


def read_train_run(path: Path, hp_index: int | None = None) -> dict[tuple[str, str], dict]:
    """{(env, agent): record} of a finished `pobax train --out` directory: the record `pobax benchmark` would write
    of it (`agent_record`), the agent matched on the benchmark's identity (else named by its memory), its metrics
    those of every update of every run (`metrics.csv`, else every chunk's `metrics/*.csv`). Where the run trained
    several hyperparameter sets, `hp_index` names one: the record is that set's (its configuration holds the set's
    values alone, its returns and curve are its runs')."""
    path = Path(path)
    run = RunDir(path)
    saved, summary = run.read_config(), run.read_summary()
    if not isinstance(summary, dict) or not isinstance(summary.get("sets"), list):
        raise ValueError(f"{str(path / 'summary.json')!r} is not a run summary pobax wrote (no list of 'sets'): the "
                         f"file is damaged; restore it")
    sets, config = summary["sets"], dict(saved["config"])
    if hp_index is None and len(sets) != 1:
        raise ValueError(f"{str(path)!r} trained {len(sets)} hyperparameter sets; a probe's arm is one: name it "
                         f"as DIR#N (N from 0 to {len(sets) - 1}), or train each set into a directory of its own")
    if hp_index is not None:
        (row,) = [r for r in sets if r.get("hp_index") == hp_index] or [None]
        if row is None:
            raise ValueError(f"{str(path)!r} has no hyperparameter set #{hp_index}: it trained {len(sets)} "
                             f"(#0 to #{len(sets) - 1})")
        # the set's values of the grid's fields (the summary's row names each), as a one-set configuration
        config.update({k: [row[k]] for k, v in config.items() if isinstance(v, list) and k in row})
        summary = dict(summary, sets=[row])
    cfg = config_from_dict(config, source=repr(str(path / "config.json")))
    chunks = sorted((path / "metrics").glob("[0-9]*.csv"))
    if (path / "metrics.csv").is_file():
        metrics = run.metrics()
    elif chunks:
        metrics = run.check_rows(ordered_metrics([read_metrics(c) for c in chunks]), path / "metrics")
    else:
        raise ValueError(f"{str(path)!r} holds no metrics (metrics.csv or metrics/*.csv): the curve needs them")
    if hp_index is not None:
        metrics = metrics[metrics["hp_index"] == hp_index].assign(hp_index=0)  # as a one-set run's
    kind = tuple(getattr(cfg, k) for k in IDENTITY)
    agent = next((a for a in gap_agents(cfg.env) if tuple(getattr(a, k) for k in IDENTITY) == kind), None) or \
        Agent(cfg.memory, f"{cfg.memory} ({cfg.observability})", cfg.observability, cfg.memory, cfg.double_critic,
              cfg.encoder)
    return {(cfg.env, agent.name): agent_record(Entry(cfg.env, agent, cfg), "none (pobax train)", path, metrics,
                                                  summary)}


def read_arm(path: Path) -> dict[tuple[str, str], dict]:
    """{(env, agent): record} of a benchmark output directory, each record checked as `pobax benchmark` checks it;
    of one record of one (`OUT/agents/ENV/AGENT.json`, a row of a shipped table as a control arm), checked the same
    way; of a `pobax train --out` directory (a summary.json in it), its run (`read_train_run`), or as `DIR#N` the
    run's hyperparameter set N."""
    head, sep, index = str(path).rpartition("#")
    if sep and index.isdigit() and (Path(head) / "summary.json").is_file():
        return read_train_run(Path(head), int(index))
    if Path(path).is_file():
        path = Path(path)
        if path.suffix != ".json" or path.parent.parent.name != "agents":
            raise ValueError(f"{str(path)!r} is not an agent record (OUT/agents/ENV/AGENT.json) nor a directory: "
                             f"pass the --out of a finished `pobax benchmark` or `pobax train`, or one of its records")
        record = read_record(path)
        return {(record["env"], record["agent"]): record}
    if (Path(path) / "summary.json").is_file():
        return read_train_run(Path(path))
    if (Path(path) / "config.json").is_file():
        raise ValueError(f"{str(path)!r} is a run that has not finished (no summary.json): resume it (`pobax train "
                         f"--resume {path}`) or give a finished one")
    records = {(r["env"], r["agent"]): r for r in read_records_in(path)}
    if not records:
        raise ValueError(f"{str(path)!r} holds no agent records (agents/ENV/AGENT.json): pass the --out of a "
                         f"finished `pobax benchmark` or `pobax train`")
    return records


def by_tenth(curve: dict, key: str) -> list[float]:
    """The curve's mean at the end of each tenth of training (the last point at or before it in which an episode
    ended; None before the first such point)."""
    steps, mean = curve["env_step"], curve[key]["mean"]
    out = []
    for t in range(1, TENTHS + 1):
        limit = steps[-1] * t / TENTHS
        i = max((j for j, s in enumerate(steps) if s <= limit and mean[j] is not None), default=None)
        out.append(None if i is None else round(float(mean[i]), 4))
    return out


def final_by_definition(r: dict, key: str) -> dict[str, float | None]:
    """The final return under three definitions: pobax's (`final`: per seed the mean over the last 10% of updates,
    then over seeds), the curve's last bin, and the last point of the curve smoothed as the paper smooths its MuJoCo
    curves (`savgol`; the bins in which an episode ended, None when fewer than the window)."""
    mean = np.asarray([np.nan if v is None else v for v in r["curve"][key]["mean"]], np.float64)
    mean = mean[np.isfinite(mean)]
    smooth = (float(savgol_filter(mean, SAVGOL_WINDOW, SAVGOL_ORDER)[-1]) if len(mean) >= SAVGOL_WINDOW else None)
    final = r[key]["mean"]  # (None where every seed diverged)
    return {"final": None if final is None else round(float(final), 4),
            "last_bin": round(float(mean[-1]), 4) if len(mean) else None,
            "savgol": None if smooth is None else round(smooth, 4)}


def factors(configs: list[dict]) -> list[str]:
    """The configuration fields whose values differ between the arms (pobax's own comparison of saved
    configurations, which reads a field a record lacks as its default)."""
    first = config_from_dict(configs[0])
    return sorted({k for c in configs[1:] for k in config_differences(c, first)})


def arm_entry(r: dict) -> dict:
    keep = ("label", "undisc", "disc", "auc", "diverged", "paper_value", "metric", "env_steps_per_s", "compile_s",
            "wall_s", "device", "jax_version", "pobax_commit", "total_steps", "num_seeds")
    entry = {k: r.get(k) for k in keep}
    entry["env_options"] = r.get("config", {}).get("env_options", [])
    entry["seed"] = r.get("config", {}).get("seed")
    entry["undisc_by_tenth_of_training"] = by_tenth(r["curve"], "undisc")
    entry["disc_by_tenth_of_training"] = by_tenth(r["curve"], "disc")
    entry["final_by_definition"] = {k: final_by_definition(r, k) for k in ("undisc", "disc")}
    return entry


def _g(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.4g}"


def _is_probe_record(path: Path) -> bool:
    """Whether `path` is a record this script wrote (a JSON object with its keys): one it may write again."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and {"what", "arms", "factors"} <= set(data)


def main(argv=None) -> int:
    p = ScriptParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arm", action="append", required=True, metavar="NAME=DIR",
                   help="an arm: its name and the --out of the `pobax benchmark` or `pobax train` that trained it "
                        "(DIR#N: set N of a run that trained several), or one record of a benchmark's "
                        "(OUT/agents/ENV/AGENT.json; two or more)")
    p.add_argument("--what", required=True, help="what the probe asks")
    p.add_argument("--command", action="append", default=[], help="a command that trained an arm (repeatable)")
    p.add_argument("--note", default="", help="anything else the record should say (devices shared, archives)")
    p.add_argument("--one-factor", action="store_true",
                   help="exit 1 when an arm differs from the first (the control) in more than one field")
    p.add_argument("--across-agents", action="store_true",
                   help="each arm holds one agent record of one environment, the agents differing (a floor beside "
                        "a memory agent: the memory is then a factor); they are compared under the agents' names")
    p.add_argument("--json", type=Path, help="write the record here")
    args = p.parse_args(argv)
    arms = {}
    for a in args.arm:
        name, sep, d = a.partition("=")
        if not sep or not name or not d:
            p.error(f"--arm {a!r}: give NAME=DIR")
        if name in arms:
            p.error(f"--arm {name!r} is given twice")
        try:
            arms[name] = read_arm(Path(d))
        except (ValueError, OSError, KeyError) as e:  # (RecordError and CheckpointError are ValueErrors)
            p.error(f"--arm {a!r}: {e}")
    if len(arms) < 2:
        p.error("a probe compares two arms or more: give --arm twice")
    keys = [set(r) for r in arms.values()]
    if args.across_agents:
        if any(len(k) != 1 for k in keys) or len({e for k in keys for e, _ in k}) != 1:
            names = {n: sorted(f"{e}/{a}" for e, a in r) for n, r in arms.items()}
            p.error(f"--across-agents needs one agent record per arm, all of one environment; got {names}")
        label = "|".join(dict.fromkeys(a for k in keys for _, a in k))  # the agents, in the arms' order
        arms = {n: {(e, label): r for (e, _), r in records.items()} for n, records in arms.items()}
        keys = [set(r) for r in arms.values()]
    if any(k != keys[0] for k in keys):
        names = {n: sorted(f"{e}/{a}" for e, a in r) for n, r in arms.items()}
        p.error(f"the arms hold different agents: {names}; each arm needs the same environments and agents "
                f"(--across-agents compares one agent per arm, e.g. a floor with a memory agent)")
    if args.json and not args.json.parent.is_dir():
        p.error(f"--json {str(args.json)!r}: its folder does not exist")
    if args.json and args.json.is_dir():
        p.error(f"--json {str(args.json)!r} is a directory: name the record's file")
    if args.json and os.path.lexists(args.json) and not _is_probe_record(args.json):
        p.error(f"--json {str(args.json)!r} holds another file (not a probe record): pass another --json, or remove it")
    out = {"what": args.what, "commands": args.command, "note": args.note, "arms": {}, "factors": {}}
    mixed, one_env = False, len({e for e, _ in keys[0]}) == 1
    print(f"{'environment':24s} {'agent':10s} {'arm':14s} {'undiscounted':>26s} {'discounted':>26s}")
    for env, agent in sorted(keys[0]):
        configs = [arms[n][(env, agent)].get("config", {}) for n in arms]
        fs = factors(configs)
        out["factors"][f"{env}/{agent}"] = fs
        mixed |= any(len(factors([configs[0], c])) > 1 for c in configs[1:])  # each arm against the first
        for n, records in arms.items():
            r = records[(env, agent)]
            entry = out["arms"][f"{n}/{agent}" if one_env else f"{n}/{env}/{agent}"] = arm_entry(r)
            u, d = r["undisc"], r["disc"]
            print(f"{env:24s} {agent:10s} {n:14s} {_g(u['mean']):>10s} [{_g(u['ci_low'])}, {_g(u['ci_high'])}]"
                  f"{_g(d['mean']):>12s} [{_g(d['ci_low'])}, {_g(d['ci_high'])}]")
            f = entry["final_by_definition"]["undisc"]
            print(f"{'':49s} undiscounted final: last bin {_g(f['last_bin'])}, Savitzky-Golay {_g(f['savgol'])}")
        print(f"  factors ({env}/{agent}): {', '.join(fs) if fs else 'none: the arms are the same configuration'}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
        print(f"written: {args.json}")
    if mixed:
        print("not a one-factor probe: an arm differs from the first in more than one field", file=sys.stderr)
        return 1 if args.one_factor else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
