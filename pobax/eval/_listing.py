"""`pobax results`: the run directories under a directory, with their state."""

import errno
import math
import os
from pathlib import Path

from ..agent import config_from_dict
from ._files import OUT_MARKERS, RUN_FILES, existing_dir, has_config
from ._records import RecordError, check_part_summary
from ._given_env import trained_env
from ._results import CheckpointError, RunDir, _is_run_config


def missing_model(path: Path) -> str:
    """What is wrong with finished run `path` whose model.eqx is gone (`load_run` refuses it, `results` lists it)."""
    return (f"{str(path)!r} is a finished run without its model.eqx (deleted or moved): its metrics and summary are "
            "there, its model is not; train it again into a new --out to evaluate it.")


#: Folders `runs_below` looks through at most (`pobax eval ~` must not walk a whole home directory).
SEARCH_DIRS = 2000


def runs_below(path: str | os.PathLike, most: int = 2) -> str:
    """For an error about `path`, a directory that is not a run directory itself: "; it holds N run directories
    (e.g. ...)" and how to list them, where run configurations lie below it (a `benchmark --out`, a `gap --out`, a
    folder of runs); "" where none do. At most `most` are named."""
    if not os.path.isdir(path):
        return ""
    found, seen = [], 0
    for folder, dirs, files in os.walk(path):  # (a home directory: the first SEARCH_DIRS folders only)
        dirs.sort()
        seen += 1
        if "config.json" in files and _is_run_config(Path(folder) / "config.json"):
            found.append(folder)
        if seen >= SEARCH_DIRS:
            break
    if not found:
        return ""
    named = ", ".join(repr(p) for p in found[:most]) + (", ..." if len(found) > most else "")
    count = f"{len(found)}" if seen < SEARCH_DIRS else f"at least {len(found)}"
    return (f"; it holds {count} run director{'y' if len(found) == 1 else 'ies'} below it ({named}): pass "
            f"{'it' if len(found) == 1 else 'those'} (`pobax results --root {path}` lists them)")


def resume_hint(path: str | os.PathLike) -> str:
    """For `--resume path` where `path` is not a run directory: how a sweep's, gap's or benchmark's directory is
    continued (its command again, with the same --out), else the run directories below it (`runs_below`)."""
    for command, marker in OUT_MARKERS.items():
        if os.path.isfile(os.path.join(path, marker)):
            return (f"; it is a `pobax {command}` directory ({marker}): run the same `pobax {command}` with --out "
                    f"{path} to continue it")
    return runs_below(path)


def list_runs(root: str | os.PathLike) -> list[dict]:
    """Every run directory under `root` (a directory with config.json and metrics): its environment and observability
    (for one given to `train(env=...)`, its classes and "given", not its configuration's), agent, number of
    hyperparameter sets and seeds, state (finished / diverged: every seed / training: another process holds it /
    resumable / incomplete / damaged: a summary, metrics table or checkpoint that does not read back, `problem` saying
    which and why in a line) and, when finished, the final discounted return of its best set by AUC (mean and 95% CI
    over seeds; None where no episode ended in the final updates)."""
    rows = []
    root = existing_dir(root, "the directory that holds the run directories")
    configs, broken = _walk(root)
    for link in broken:  # (a run or set directory replaced by a link that leads nowhere: it may hide a run)
        target = os.readlink(link)
        try:
            os.stat(link)
            what = "leads to nothing"  # (put there while it was read)
        except OSError as e:
            what = "leads back to itself" if e.errno == errno.ELOOP else "leads to nothing"
        rows.append({"path": str(link), "env": "?", "observability": "?", "agent": "?", "sets": 0, "seeds": 0,
                     "disc_return": None, "ci_low": None, "ci_high": None, "state": "damaged",
                     "problem": f"{str(link)!r}, in a directory pobax wrote, is a symbolic link to {target!r}, which "
                                f"{what}: restore what stood there, or remove the link."})
    for cfg_path in configs:
        rd = RunDir(cfg_path.parent)
        row = {"path": str(rd.path), "env": "?", "observability": "?", "agent": "?", "sets": 0, "seeds": 0,
               "disc_return": None, "ci_low": None, "ci_high": None}
        if not _is_run_config(cfg_path):  # another program's config.json, or a run's damaged one
            if not os.path.lexists(cfg_path):  # gone since the walk: a run its trainer discarded (failed at its start)
                continue
            if any((rd.path / name).exists() for name in RUN_FILES):
                try:
                    has_config(rd.path)  # a link to nothing or a directory, named as one
                    problem = f"{str(cfg_path)!r} is not a run configuration pobax wrote: restore it."
                except CheckpointError as e:
                    problem = _line(e)
                rows.append(row | {"state": "damaged", "problem": problem})
            continue
        try:  # as every command reads it: a field edited to another type is refused there, naming the file
            record = rd.read_config()
            cfg = config_from_dict(record["config"], source=repr(str(cfg_path)))
        except ValueError as e:
            rows.append(row | {"state": "damaged", "problem": _line(e)})
            continue
        except OSError as e:
            if not os.path.lexists(cfg_path):  # as above: discarded since it was looked at
                continue
            rows.append(row | {"state": "damaged", "problem": f"{str(cfg_path)!r} cannot be read ({e.strerror or e})."})
            continue
        env, observability = trained_env(record)
        row.update(env=env, observability=observability, sets=len(cfg.grid()), seeds=cfg.num_seeds,
                   agent=cfg.memory + ("+ld" if cfg.double_critic else ""))
        if os.path.lexists(rd.path / "summary.json"):  # (a broken link is a damaged summary, not none)
            _finished(rd, row)
        elif rd.held_elsewhere():  # (its checkpoint may be mid-replacement: not read)
            row["state"] = "training"
        else:
            try:
                rd.check_unfinished()  # what a resume checks before it compiles
            except (CheckpointError, OSError) as e:
                if (rd.path / "summary.json").exists():  # it finished while it was read, and cleared its checkpoint
                    _finished(rd, row)
                else:
                    row.update(state="damaged", problem=_line(e))
            else:
                row["state"] = "resumable" if (rd.path / "checkpoint.json").exists() else "incomplete"
        rows.append(row)
    return sorted(rows, key=lambda row: row["path"])


def _walk(root: Path) -> tuple[list[Path], list[Path]]:
    """The config.json paths below `root` (a directory there too: a damaged run; a link to nothing, which os.walk,
    unlike rglob, lists), following links to directories, each real directory once (a link to a folder above is not
    a loop); and the links that lead nowhere or back to themselves in a sweep's, gap's or benchmark's --out, or a
    folder below one outside its runs, where every entry is pobax's (a run's own row names its damaged files).
    Sorted."""
    configs, broken, seen, owned = [], [], set(), set()
    for folder, dirs, files in os.walk(root, followlinks=True):
        dirs.sort()  # (which of two paths to one directory is listed: the first in order)
        real = os.path.realpath(folder)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        if "config.json" in files or "config.json" in dirs:
            configs.append(Path(folder) / "config.json")
            continue
        if os.path.dirname(folder) in owned or any(marker in files for marker in OUT_MARKERS.values()):
            owned.add(folder)
            broken += [Path(folder) / name for name in files
                       if os.path.islink(os.path.join(folder, name)) and not os.path.exists(os.path.join(folder, name))]
    return sorted(configs), sorted(broken)


def _finished(rd: RunDir, row: dict) -> None:
    """`row`'s state and return for a finished run (its summary.json written): damaged where summary.json or
    metrics.csv (what plot and eval read, checked as they check it) does not read back; listed, not fatal for the
    other runs."""
    path = rd.path / "summary.json"
    try:
        s = rd.read_summary()
        check_part_summary(s, path, kind="a run's summary", fix="restore it")
        best_set = s["sets"][s["best_by_auc"]]
        best, diverged = best_set["disc_return"], best_set["diverged"]
        mean = best["mean"]
    except (CheckpointError, RecordError) as e:
        row.update(state="damaged", problem=_line(e))
        return
    except OSError as e:  # e.g. a link to itself
        row.update(state="damaged", problem=f"{str(path)!r} cannot be read ({e.strerror or e}): restore it.")
        return
    try:  # (a sweep part copied without its metrics and model, `benchmark --merge`: its summary is the result)
        if any(os.path.lexists(rd.path / name) for name in ("metrics.csv", "model.eqx", "metrics")):
            rd.metrics()
    except (ValueError, OSError) as e:
        row.update(state="damaged", problem=_line(e))
        return
    if os.path.lexists(rd.path / "metrics.csv") and not os.path.lexists(rd.path / "model.eqx"):
        row.update(state="damaged", problem=missing_model(rd.path))
        return
    if isinstance(mean, (int, float)) and math.isfinite(mean):
        row.update(state="finished", disc_return=mean, ci_low=best["ci_low"], ci_high=best["ci_high"])
    elif diverged >= row["seeds"] > 0:  # every seed of its best set (so of every set) diverged
        row["state"] = "diverged"
    else:  # finished, but no episode ended in the final updates (too few steps): no return to show
        row["state"] = "finished"


def _line(e: Exception) -> str:
    return str(e).splitlines()[0] if str(e) else type(e).__name__
