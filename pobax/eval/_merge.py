"""`pobax benchmark --merge`: the finished agents' records of other benchmark output directories, into one."""

import datetime
from pathlib import Path

from ._plan import BenchmarkError, benchmark_dir
from ._records import check_record
from ._report import write_results
from ._results import atomic_write_text, read_json, writable_dir, write_json


def merge_results(out: str | Path, sources: tuple[str | Path, ...], command: str | None = None) -> dict:
    """Copy the finished agents' records of other benchmark output directories (`sources`, e.g. brought back from
    other machines) into `out` and write the results; nothing trains. A record `out` already has is kept (a record
    never changes): a source's different record for the same agent is reported, not copied. `out`'s benchmark.json
    gains the sources' environments and calls (each marked with the directory it came from) and a call for the
    merge. Returns {"added": [...], "kept": [...], "files": [...]} (records as "ENV/NAME")."""
    out = benchmark_dir(out)
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
    for src in metas:  # every record is checked before anything is copied or written
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
