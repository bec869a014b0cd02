"""`pobax benchmark --merge`: the finished agents' records of other benchmark output directories, into one."""

import datetime
import json
import os
from pathlib import Path

from ..agent._config import NUMERIC, saved_config_differences
from ._args import as_path, check_names
from ._files import check_figure_path
from ._locks import shared_files
from ._plan import BenchmarkError, benchmark_dir, one_budget, record_budget, shown_budget
from ._records import RecordError, check_part_config, check_part_summary, check_record, read_meta, records_by_path
from ._report import write_results
from ._results import RunDir, atomic_write_text, read_json, writable_dir, write_json
from ._seal import SEAL, SEALS


def _resolved(path: Path, flag: str) -> Path:
    try:
        return path.resolve()
    except (RuntimeError, OSError):  # (a symlink loop: RuntimeError up to Python 3.12, OSError after)
        raise BenchmarkError(f"{flag} {str(path)!r} is a symbolic link that leads back to itself: pass a "
                             f"directory.") from None


def merge_results(out: str | Path, sources: tuple[str | Path, ...], command: str | None = None) -> dict:
    """Copy the finished agents' records of other benchmark output directories (`sources`, e.g. brought back from
    other machines) into `out` and write the results; nothing trains. A record `out` already has is kept (a record
    never changes): a source's different record for the same agent is reported, not copied. `out`'s benchmark.json
    gains the sources' environments and calls (each marked with the directory it came from) and a call for the
    merge. The finished parts of protocol sweeps (`runs/ENV/NAME-sweep/PART/`: their configuration, summary and
    sessions, all a later call needs to reuse them) are copied where `out` has not finished the part (an unfinished
    part of the same configuration is superseded; a part of other steps, seeds or sizes than the sweep's other parts,
    or trained on another device kind, commit or JAX version, is refused), so that a protocol trained partly
    elsewhere continues in `out`. A source copied from `out` brings back `out`'s own calls: those are not listed
    twice. Returns {"added": [...],
    "kept": [...], "parts": [...], "kept_parts": [...], "why": [...], "files": [...]} (records as "ENV/NAME", parts as
    "ENV/NAME-sweep/PART"; `kept`: records of another training than the one kept, from `out` or the first source
    that brought it; `kept_parts`: parts `out` keeps because a source's has another configuration, or that another
    process is training in `out`; `why`: a line for each of those, naming the directories). Paths may start with
    `~`; a single path as `sources` (read one character at a time) is refused."""
    check_names("merge_results", "sources", sources, BenchmarkError, what="directories")
    out = benchmark_dir(as_path("merge_results", "out", out, BenchmarkError, what="a directory path"))
    if not sources:
        raise BenchmarkError("--merge needs at least one benchmark output directory to merge from.")
    sources = [as_path("merge_results", "sources", src, BenchmarkError, what="a directory path") for src in sources]
    metas = {}
    out_resolved = _resolved(out, "--out")
    for src in sources:
        if _resolved(src, "--merge") == out_resolved:
            raise BenchmarkError(f"--merge {str(src)!r} is --out itself; pass the directories to merge from.")
        if _resolved(src, "--merge") in out_resolved.parents:  # (in its agents/, --out's files read as its records)
            raise BenchmarkError(f"--out {str(out)!r} is inside --merge {str(src)!r}: the merge would write into a "
                                 f"directory it reads; pass an --out outside it.")
        if not (src / "benchmark.json").is_file():
            raise BenchmarkError(f"--merge {str(src)!r} has no benchmark.json: pass a directory that `pobax "
                                 f"benchmark` wrote.")
        metas[src] = read_meta(src / "benchmark.json")
        _check_folders(src)
    _check(out, metas)  # every record and finished sweep part, before anything is written...
    check_figure_path(out / "benchmark.png", "the figure")  # (before anything is copied)
    out.mkdir(parents=True, exist_ok=True)
    writable_dir(out)
    meta_path = out / "benchmark.json"
    with shared_files(out):  # another process may be writing into the same --out
        protocol = _check(out, metas)  # ...and again, with what another process wrote into --out meanwhile
        meta = read_meta(meta_path)
        meta["protocol"] = protocol
        if not meta_path.exists():  # first: a merge killed while copying leaves a directory pobax reads
            write_json(meta_path, meta)
        added, same, kept, parts, kept_parts, why = [], [], [], [], [], []
        origin = {}  # a record this merge copied: the source it came from
        for src, src_meta in metas.items():
            for path in sorted((src / "agents").glob("*/*.json")):
                name, dst = f"{path.parent.name}/{path.stem}", out / "agents" / path.parent.name / path.name
                if dst.exists():
                    differ = _differing(read_json(dst), read_json(path))
                    if differ:
                        kept.append(name)
                        why.append(f"kept the record of {name} from {str(origin.get(name, out))!r}, not "
                                   f"{str(src)!r}'s (they differ in {', '.join(differ[:4])}"
                                   f"{' …' if len(differ) > 4 else ''})")
                    else:  # (one an earlier merge of it copied, killed before its call was written: named here)
                        same.append(name)
                    continue
                origin[name] = src
                dst.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_text(dst, _checked_text(path, protocol))  # (its sweep table: write_results rebuilds it)
                added.append(name)
            for summary in sorted((src / "runs").glob("*/*-sweep/*/summary.json")):
                part = summary.parent
                dst, name = out / part.relative_to(src), str(part.relative_to(src / "runs"))
                if (dst / "summary.json").exists() or not (part / "config.json").is_file():
                    continue
                if dst.is_dir() and RunDir(dst).held_elsewhere():  # another process trains it: left to it
                    kept_parts.append(name)
                    why.append(f"left sweep part {name} to the process training it in {str(dst)!r}")
                    continue
                if (dst / "config.json").is_file() \
                        and read_json(dst / "config.json") != read_json(part / "config.json"):
                    kept_parts.append(name)  # another configuration: keep it
                    why.append(f"kept {str(out)!r}'s sweep part {name}: {str(src)!r}'s has another configuration")
                    continue
                dst.mkdir(parents=True, exist_ok=True)
                for file in ("config.json", "sessions.json", "summary.json"):  # the summary last: it marks it finished
                    if (part / file).is_file():
                        atomic_write_text(dst / file, (part / file).read_text())
                parts.append(name)
            meta["envs"] = list(dict.fromkeys([*meta["envs"], *src_meta.get("envs", [])]))
            held_calls = {_call_key(c) for c in meta["calls"]}
            meta["calls"] += [dict(c, merged_from=str(src)) for c in src_meta.get("calls", [])
                              if _call_key(c) not in held_calls]
        meta["calls"].append({"time": datetime.datetime.now().isoformat(timespec="seconds"), "command": command,
                              "merged": [str(s) for s in metas], "added": added, "identical": same,
                              "parts": parts})
        write_json(meta_path, meta)
    return {"added": added, "kept": kept, "parts": parts, "kept_parts": kept_parts, "why": why,
            "files": write_results(out)}


def _check(out: Path, metas: dict) -> str:
    """Refuse (BenchmarkError) what the sources `metas` ({directory: its benchmark.json}) would bring into `out` that
    `out` could not hold: another protocol, a record of another budget than `out`'s (or another source's) records of
    its environment, a damaged record or sweep part, a part that `out`'s sweep could not continue from. Returns the
    protocol `out` holds after the merge."""
    meta_path = out / "benchmark.json"
    held = read_meta(meta_path).get("protocol", "registry") if meta_path.exists() else None
    protocols = {str(src): m.get("protocol", "registry") for src, m in metas.items()}
    for src, protocol in protocols.items():  # one output directory holds one protocol
        if protocol != (held or next(iter(protocols.values()))):
            raise BenchmarkError(f"--merge {src!r} holds the {protocol!r} protocol's results and --out "
                                 f"{str(out)!r} the {held or next(iter(protocols.values()))!r} protocol's: merge "
                                 f"each protocol into its own --out.")
    protocol = held or next(iter(protocols.values()))
    budgets = {}  # per environment, its records' (budget, steps, seeds, plan): one table row trains them alike
    for path, record in records_by_path(out):  # out's own too
        budgets.setdefault(record["env"], []).append((record_budget(record, protocol), path))
    sweeps = {}  # per sweep directory in out, the part that fixed its settings: one sweep trains at one budget
    for src in metas:  # every record and finished sweep part is checked before anything is copied or written
        for path, record in records_by_path(src):
            if (out / "agents" / path.parent.name / path.name).exists():
                continue  # kept as it is
            known, mine = budgets.setdefault(record["env"], []), record_budget(record, protocol)
            for other, where in known:
                if not one_budget(mine, other):
                    raise BenchmarkError(f"{str(path)!r} was trained at {shown_budget(mine)}, {str(where)!r} at "
                                         f"{shown_budget(other)}: one table holds one budget per environment; merge it "
                                         f"into another --out.")
            known.append((mine, path))
        for path in sorted((src / "runs").glob("*/*-sweep/*/summary.json")):
            check_part_config(path.parent)
            check_part_summary(RunDir(path.parent).read_summary(), path)
            config, provenance = read_json(path.parent / "config.json"), _part_provenance(path.parent)
            if not isinstance(config, dict) or not isinstance(config.get("config"), dict):
                raise BenchmarkError(f"{str(path.parent)!r}: its config.json is not one pobax wrote; restore it, or "
                                     f"move the part aside.")
            if not (out / path.relative_to(src)).exists():
                _check_one_sweep(path.parent, config["config"], provenance, out / path.parent.parent.relative_to(src),
                                 sweeps)
    return protocol


def _checked_text(path: Path, protocol: str) -> str:
    """A source record's text, checked as it is copied (`check_record`): what another process changed there after the
    merge's checks is refused by name, not copied unchecked."""
    text = path.read_text()
    try:
        record = json.loads(text)
    except ValueError:
        raise RecordError(f"{str(path)!r} is not JSON: it changed while it was merged; restore it, then run the same "
                          f"merge again, which completes this one.") from None
    check_record(record, path, protocol)
    return text


def _check_folders(src: Path) -> None:
    """A BenchmarkError naming what stands where `src` keeps its records' folders (agents/, agents/ENV/) and is not
    a directory (a file, a link to nothing or to itself): read as no records, it would merge nothing and say so."""
    agents = src / "agents"
    for path in [agents] + (sorted(agents.iterdir()) if agents.is_dir() else []):
        if os.path.lexists(path) and not path.is_dir():
            raise BenchmarkError(f"--merge {str(src)!r}: {str(path)!r} is not a directory (a file, or a link to "
                                 f"nothing or to itself), where the records' folders stand: restore it, or move it "
                                 f"aside.")


def _part_provenance(part: Path) -> list[tuple[str, str, str]]:
    """The (device, commit, JAX version) of every session that trained the sweep part in `part` (its sessions.json),
    sorted, without repeats; a sessions.json that is not a list of objects is refused by name."""
    sessions = read_json(part / "sessions.json") if (part / "sessions.json").is_file() else []
    if not isinstance(sessions, list) or not all(isinstance(x, dict) for x in sessions):
        raise BenchmarkError(f"{str(part)!r}: its sessions.json is not one pobax wrote; restore it, or move the part "
                             f"aside.")
    return sorted({(str(x.get("device")), str(x.get("pobax_commit")), str(x.get("jax"))) for x in sessions})


def _shown_provenance(provenance: list[tuple[str, str, str]]) -> str:
    return " + ".join(f"{device} ({commit}, JAX {jax})" for device, commit, jax in provenance) or "nothing recorded"


def _check_one_sweep(part: Path, config: dict, provenance: list, sweep: Path, sweeps: dict) -> None:
    """Refuse a finished sweep part that `out`'s sweep directory `sweep` could not continue from: one whose settings
    other than the hyperparameters (steps, seeds, sizes, environment options: every field but `NUMERIC`'s, a field
    a configuration lacks counting as its default) differ from those of `out`'s finished parts of that sweep or of
    a part this merge copies there (e.g. a part of the smoke budget into the paper budget's sweep, which the next
    benchmark would refuse by name); or one trained on another device kind, commit or JAX version (`provenance`,
    from its sessions.json) than those parts: the agent's record would then read as trained across several, which
    `protocol_table` keeps out of the protocol's table."""
    if sweep not in sweeps:
        sweeps[sweep] = (part, config, provenance)
        for done in sorted(sweep.glob("*/summary.json")):
            theirs = read_json(done.parent / "config.json") if (done.parent / "config.json").is_file() else None
            if isinstance(theirs, dict) and isinstance(theirs.get("config"), dict):
                sweeps[sweep] = (done.parent, theirs["config"], _part_provenance(done.parent))
                break
    first, theirs, their_provenance = sweeps[sweep]
    differ = [k for k in saved_config_differences(config, theirs) if k not in NUMERIC]
    if differ:
        k = differ[0]
        shown = lambda c: repr(c[k]) if k in c else "its default"  # noqa: E731  (a field added since)
        raise BenchmarkError(f"{str(part)!r} was trained with {k} {shown(config)}, {str(first)!r} with "
                             f"{shown(theirs)}: the parts of one sweep train at one budget; merge it into another "
                             f"--out.")
    if provenance != their_provenance:
        raise BenchmarkError(f"{str(part)!r} was trained on {_shown_provenance(provenance)}, {str(first)!r} on "
                             f"{_shown_provenance(their_provenance)}: an agent whose sweep ran on several device "
                             f"kinds, commits or JAX versions stays out of the protocol's table; train the part again "
                             f"where the others trained, or merge it into another --out.")


#: A record's fields that differ between two trainings of the same runs (when and how fast it ran, its seal).
_NOT_TRAINING = frozenset({"written", "wall_s", "compile_s", "env_steps_per_s", SEAL, SEALS})


def _differing(a, b) -> list[str]:
    """The fields in which two records of one agent differ, left out those that differ between two trainings of the
    same runs (`_NOT_TRAINING`): empty where both hold the same training."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [] if a == b else ["their whole contents"]
    return sorted(k for k in {*a, *b} - _NOT_TRAINING if a.get(k, ...) != b.get(k, ...))


def _call_key(call: dict) -> tuple:
    """A call as the directory it ran in wrote it (the mark a merge adds left out)."""
    return tuple(sorted((k, repr(v)) for k, v in call.items() if k != "merged_from"))
