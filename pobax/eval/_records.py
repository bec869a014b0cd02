"""A benchmark record (`agents/ENV/NAME.json`, one finished agent) checked before it is used: `benchmark --merge`
copies nothing until every record it would copy reads as one, and a benchmark or its tables refuse an edited or
damaged record in a line naming it."""

import math
from pathlib import Path

from ..agent._config import NUMERIC
from ._files import CheckpointError, has_config, json_digest
from ._seal import SEAL, SEALS, without_seal
from ._results import read_json


class RecordError(ValueError):
    """A file that is not a benchmark record pobax wrote; the message (one line) names it."""


_TEXT = ("env", "agent", "observability", "memory", "budget", "metric")
#: The protocols a benchmark directory holds (`benchmark.json`'s "protocol"; a record's, "registry" where absent).
PROTOCOLS = ("registry", "paper")
#: Counts a record holds: whole numbers JSON and float64 carry exactly.
_EXACT = 2 ** 53


def seal_record(record: dict) -> dict:
    """`record` as written: saying its pobax seals records (`SEALS`), sealed with the SHA-256 of its contents
    (`SEAL`), so that a record edited after it was written, or its seal removed, is refused (`check_record`)."""
    body = {**without_seal(record), SEALS: True}
    return {**body, SEAL: json_digest(body)}
_STATS = ("disc", "undisc", "auc")
#: A summary's statistics per set, the records' disc, undisc and auc.
_SET_STATS = ("return", "disc_return", "disc_return_auc")


def check_record(record, path: str | Path, protocol: str | None = None) -> None:
    """Raise RecordError unless `record` (read from `path`) has what the results table, report and figure read: its
    environment and agent (matching the file's place, ENV/NAME.json), their settings, the returns' statistics and
    the learning curve; a sealed record (`seal_record`) as written; its protocol `protocol` (its directory's) where
    given, with its selection and evaluation where that is the paper's."""
    def bad(what: str) -> RecordError:
        return _not_written(path, "a benchmark record", what, "restore it, or move it out of its directory")

    if not isinstance(record, dict):
        raise bad(f"a JSON {type(record).__name__}, not an object")
    if SEAL in record:
        if record[SEAL] != json_digest(without_seal(record)):
            raise RecordError(f"{str(path)!r} was edited after it was written (it no longer matches its SHA-256): "
                              f"restore it, or move it out of its directory to train the agent again.")
    elif record.get(SEALS) is True:
        raise RecordError(f"{str(path)!r} has no seal ({SEAL!r}), though the pobax that wrote it seals every record: "
                          f"the seal was removed, so the record may have been edited; restore it, or move it out of "
                          f"its directory to train the agent again.")
    mine = record.get("protocol", "registry")
    if mine not in PROTOCOLS:
        raise bad(f"protocol is {mine!r}, not one of {', '.join(PROTOCOLS)}")
    if protocol is not None and mine != protocol:
        raise RecordError(f"{str(path)!r} is a record of the {mine!r} protocol and its directory's benchmark.json "
                          f"says {protocol!r}: one of the two was edited; restore it, or move the record out of its "
                          f"directory.")
    if (mine == "paper") != ("selection" in record):
        raise bad("a paper-protocol record without its selection" if mine == "paper" else
                  "a selection in a registry record")
    missing = [k for k in (*_TEXT, "double_critic", "total_steps", "num_seeds", *_STATS, "curve", "config",
                           "env_steps_per_s", "paper_value") if k not in record]
    if missing:
        raise bad("no " + ", ".join(missing[:4]) + (" …" if len(missing) > 4 else ""))
    for k in _TEXT:
        if not isinstance(record[k], str) or not record[k]:
            raise bad(f"{k} is {record[k]!r}")
    p = Path(path)
    if (p.parent.name, p.stem) != (record["env"], record["agent"]):
        raise bad(f"it is {record['env']}/{record['agent']}, filed as {p.parent.name}/{p.stem}")
    if not isinstance(record["double_critic"], bool):
        raise bad(f"double_critic is {record['double_critic']!r}")
    for k in ("total_steps", "num_seeds"):
        if not isinstance(record[k], int) or isinstance(record[k], bool) or not 1 <= record[k] < _EXACT:
            raise bad(f"{k} is {record[k]!r}")
    for k in ("label", "device", "jax_version", "pobax_commit"):  # what the tables print, by name
        if not isinstance(record.get(k), str):
            raise bad(f"{k} is {record.get(k)!r}")
    for k in (*_TEXT, "label", "device", "jax_version", "pobax_commit"):  # one line in a table's cell
        if not record[k].isprintable() or "|" in record[k]:
            raise bad(f"{k} {record[k]!r} holds a control character or '|', which would break the tables")
    for k in _STATS:
        block = record[k]
        if not isinstance(block, dict) or not all(s in block and _number(block[s])
                                                  for s in ("mean", "ci_low", "ci_high")):
            raise bad(f"{k} is not a mean with its confidence interval")
        seeds = block.get("per_seed", [])
        if not isinstance(seeds, list) or not all(_number(v) for v in seeds):
            raise bad(f"{k}'s per_seed is not a list of numbers")
    if not isinstance(record["config"], dict):
        raise bad(f"config is {record['config']!r}")
    if "selection" in record:  # a protocol record: its sweep's configuration and its evaluation's seeds
        sel, ev = record["selection"], record.get("evaluation")
        if not isinstance(sel, dict) or not isinstance(sel.get("config"), dict):
            raise bad("its selection has no config object")
        sets = sel.get("sets", [{}])  # the sweep table (`sweep_csv`)
        if not isinstance(sets, list) or not sets or not all(isinstance(row, dict) and row.keys() == sets[0].keys()
                                                             and all(map(_number, row.values())) for row in sets):
            raise bad("its selection's sets are not a table of numbers")
        if not isinstance(ev, dict) or not all(isinstance(ev.get(k), int) and not isinstance(ev[k], bool)
                                               and 0 <= ev[k] < _EXACT for k in ("seed", "num_seeds")):
            raise bad("its evaluation has no seed and num_seeds")
    curve = record["curve"]
    steps = curve.get("env_step") if isinstance(curve, dict) else None
    if not isinstance(steps, list) or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < _EXACT
                                              for v in steps):
        raise bad("its curve has no env_step list")
    for key in ("disc", "undisc"):
        block = curve.get(key)
        if not isinstance(block, dict) or any(not isinstance(block.get(s), list) or len(block[s]) != len(steps)
                                              or not all(_number(v) for v in block[s])
                                              for s in ("mean", "low", "high")):
            raise bad(f"its curve's {key} is not mean, low and high at every env_step")
    for k in ("env_steps_per_s", "paper_value"):  # (null where there is none)
        if not _number(record[k]):
            raise bad(f"{k} is {record[k]!r}")
    if not isinstance(record.get("reference", {}), (dict, type(None))):
        raise bad(f"reference is {record['reference']!r}, not an object")
    metrics = record.get("episode_metrics", {})
    if not isinstance(metrics, dict) or not all(isinstance(v, dict) and _number(v.get("mean"))
                                                for v in metrics.values()):
        raise bad("its episode_metrics are not per-episode quantities, each with its mean")


def sweep_csv(sets: list[dict]) -> str:
    """A protocol record's sweep table (its selection's sets: each set's hyperparameters, AUC, final returns,
    diverged runs and seeds) as `agents/ENV/NAME.sweep.csv` holds it."""
    columns = list(sets[0])
    return ",".join(columns) + "\n" + "".join(
        ",".join("" if row[c] is None else f"{row[c]:.6g}" if isinstance(row[c], float) else str(row[c])
                 for c in columns) + "\n" for row in sets)


def read_records_in(out: str | Path) -> list[dict]:
    """Every record under `out/agents/` (ENV/NAME.json, in path order), each checked (`check_record`), of the
    protocol `out`'s benchmark.json holds."""
    return [record for _, record in records_by_path(out)]


def records_by_path(out: str | Path) -> list[tuple[Path, dict]]:
    """`read_records_in`'s records, each with its path (from one listing of the folder: a record another process
    writes meanwhile is either read with its path or not at all)."""
    protocol = read_meta(Path(out) / "benchmark.json").get("protocol", "registry")
    return [(path, read_record(path, protocol)) for path in sorted((Path(out) / "agents").glob("*/*.json"))]


def read_record(path: str | Path, protocol: str | None = None) -> dict:
    """One record, `OUT/agents/ENV/NAME.json`, checked (`check_record`) as of `protocol`, by default the one OUT's
    benchmark.json holds."""
    path = Path(path)
    if protocol is None:
        protocol = read_meta(path.parents[2] / "benchmark.json").get("protocol", "registry")
    record = read_json(path)
    check_record(record, path, protocol)
    return record


def check_part_config(run: Path) -> None:
    """A finished sweep part (its summary.json there) keeps its config.json, which the selection, a merge and a
    changed split read: a CheckpointError naming it where it is gone (not the system's "[Errno 2] No such file"), or
    where it is a link to nothing (`has_config`)."""
    if not has_config(run):
        raise CheckpointError(f"{str(run / 'config.json')!r} is missing from a finished sweep part (summary.json): "
                              f"restore it, or move the part directory aside to train the part again.")


def check_part_summary(summary, path, grid: dict | None = None, kind: str = "a sweep part's summary",
                       fix: str = "restore it, or move its part directory aside to train the part again") -> None:
    """Raise RecordError unless `summary` (read from a sweep part's, or a run's, `path`) has what the selection
    reads: its sets, each with its hyperparameters as numbers (`grid`'s axes required, where given), its diverged
    runs and the mean of its returns and AUC. A summary edited or damaged into another shape is refused naming its
    file (`kind`, with `fix`), before anything is selected."""
    def bad(what: str) -> RecordError:
        return _not_written(path, kind, what, fix)

    sets = summary.get("sets") if isinstance(summary, dict) else None
    if not isinstance(sets, list) or not sets:
        raise bad("no sets")
    sessions = summary.get("sessions", [])
    if not isinstance(sessions, list) or not all(isinstance(x, dict) for x in sessions):
        raise bad("its sessions are not a list of objects")
    if not _number(summary.get("wall_s")):
        raise bad(f"wall_s is {summary.get('wall_s')!r}")
    number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    for i, row in enumerate(sets):
        if not isinstance(row, dict):
            raise bad(f"set {i} is not an object")
        missing = [k for k in (*(grid or ()), "hp_index", "diverged", *_SET_STATS) if k not in row]
        if missing:
            raise bad(f"set {i} has no {', '.join(missing)}")
        hps = {*(grid or ()), *(k for k in NUMERIC if k in row)}  # the grid's axes, else every hyperparameter shown
        if not all(number(row[k]) for k in hps) or not isinstance(row["diverged"], int) or row["diverged"] < 0:
            raise bad(f"set {i} has a hyperparameter or diverged count that is not a number")
        if row["hp_index"] != i:
            raise bad(f"set {i}'s hp_index is {row['hp_index']!r}")
        for k in _SET_STATS:  # what the records and the sweep tables copy: NaN where no seed is left
            block = row[k]
            if not isinstance(block, dict) or not all(number(block.get(s)) for s in ("mean", "ci_low", "ci_high")):
                raise bad(f"set {i} has a {k} without its mean and confidence interval")
            if not isinstance(block.get("per_seed", []), list) or not all(number(v) for v in block.get("per_seed", [])):
                raise bad(f"set {i}'s {k} per_seed is not a list of numbers")
    best = summary.get("best_by_auc")
    if not (isinstance(best, int) and not isinstance(best, bool) and 0 <= best < len(sets)):
        raise bad(f"best_by_auc {best!r} is not one of its sets 0 … {len(sets) - 1}")
    for k in ("steps_per_s", "compile_s"):
        if not (summary.get(k) is None or number(summary[k])):
            raise bad(f"{k} is {summary[k]!r}")


def _number(v) -> bool:
    """A number, or None (a statistic that has none: e.g. every seed diverged)."""
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))


def read_meta(path: str | Path) -> dict:
    """A benchmark directory's `benchmark.json` (its protocol, environments and calls), checked: a file edited or
    damaged into another shape is refused in a line naming it; a missing one reads as an empty directory's."""
    path = Path(path)
    if not path.exists():
        return {"envs": [], "calls": []}
    meta = read_json(path)

    def bad(what: str) -> RecordError:
        return _not_written(path, "a benchmark.json", what, "restore it, or pass another directory")

    if not isinstance(meta, dict):
        raise bad(f"a JSON {type(meta).__name__}, not an object")
    if not isinstance(meta.get("envs"), list) or not all(isinstance(e, str) for e in meta["envs"]):
        raise bad("envs is not a list of environment IDs")
    if not isinstance(meta.get("calls"), list) or not all(isinstance(c, dict) for c in meta["calls"]):
        raise bad("calls is not a list of calls")
    if meta.get("protocol", "registry") not in PROTOCOLS:
        raise bad(f"protocol is {meta['protocol']!r}, not one of {', '.join(PROTOCOLS)}")
    return meta


def _not_written(path, kind: str, what: str, fix: str) -> RecordError:
    return RecordError(f"{str(path)!r} is not {kind} pobax wrote ({what}); {fix}.")
