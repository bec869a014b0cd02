"""The seal of a finished run's summary: the SHA-256 of the summary, its configuration and its finished files, written
with the summary (`seal_summary`) and checked by every reader (`check_seal`), so that a run edited or damaged after it
finished is refused by name instead of reported."""

import math
from pathlib import Path
from typing import Any

from ._files import CheckpointError, json_digest, plain, read_json, sha256_of


#: The key of a finished run's summary.json that holds its seal (`seal_summary`).
SEAL = "sha256"
#: The key of a session (sessions.json, and the summary's own list) that says its pobax sealed every summary it wrote:
#: a summary without a seal in a run that such a session trained had its seal removed.
SEALS = "seals"
#: A finished run's files whose SHA-256 its summary's seal holds, beside the summary's own.
SEALED_FILES = ("metrics.csv", "model.eqx", "obs_norm.eqx")


def seal_summary(summary: dict, run: Path) -> dict:
    """`summary` with its seal: the SHA-256 of its own contents, of the run's configuration (config.json, as JSON:
    its layout is free) and of its finished files (`SEALED_FILES`) in the directory `run`, so that a summary,
    configuration, metrics table or model edited after the run finished is refused (`check_seal`) instead of
    reported."""
    body = without_seal(summary)
    config = {"config.json": json_digest(read_json(run / "config.json"))} if (run / "config.json").is_file() else {}
    return {**body, SEAL: {"summary.json": json_digest(body), **config,
                           **{name: sha256_of(run / name) for name in SEALED_FILES if (run / name).is_file()}}}


def _config_digest(run: Path) -> str | None:
    try:
        return json_digest(read_json(run / "config.json"))
    except (CheckpointError, OSError):
        return None


def without_seal(summary: Any) -> Any:
    """A summary as training returned it: its seal left out."""
    return {k: v for k, v in summary.items() if k != SEAL} if isinstance(summary, dict) else summary


def check_seal(summary: Any, run: Path) -> None:
    """Raise CheckpointError naming the file unless a sealed summary read from `run`'s summary.json, and each sealed
    file still there, are as the run finished. A file gone is not checked (a sweep part copied without its metrics
    and model); a summary without a seal was written before pobax sealed them; a seal without config.json before
    pobax sealed that: then config.json must agree with what the summary shows of it (`check_config_of`). A summary
    without a seal whose sessions (its own list, or the run's sessions.json) were trained by a pobax that seals
    (`SEALS`) had its seal removed: refused."""
    if not isinstance(summary, dict):
        return
    if SEAL not in summary:
        if _sealing_sessions(summary, run):
            raise CheckpointError(f"{str(run / 'summary.json')!r} has no seal ({SEAL!r}), though the pobax that "
                                  f"trained the run seals every summary it writes: the seal was removed, so the file "
                                  f"may have been edited; restore it, or move the run directory aside to train it "
                                  f"again.")
        return
    seal, path = summary[SEAL], run / "summary.json"
    if not isinstance(seal, dict) or not all(isinstance(v, str) for v in seal.values()):
        raise CheckpointError(f"{str(path)!r} holds a damaged seal ({SEAL!r}): restore it, or move the run "
                              f"directory aside to train it again.")
    if seal.get("summary.json") != json_digest(without_seal(summary)):
        raise CheckpointError(f"{str(path)!r} was edited after its run finished (it no longer matches its SHA-256): "
                              f"restore it, or move the run directory aside to train it again.")
    if "config.json" not in seal:
        check_config_of(summary, run)  # what the (sealed) summary shows of the configuration
    elif (run / "config.json").is_file() and seal["config.json"] != _config_digest(run):
        raise CheckpointError(f"{str(run / 'config.json')!r} differs from the configuration its run finished with "
                              f"(SHA-256 in summary.json): the file was edited or damaged; restore it, or move the "
                              f"run directory aside to train it again.")
    for name in SEALED_FILES:
        if plain(run / name).is_file() and seal.get(name) != sha256_of(run / name):
            raise CheckpointError(f"{str(run / name)!r} differs from the file its run finished with (SHA-256 in "
                                  f"summary.json): the file was edited or damaged; restore it, or move the run "
                                  f"directory aside to train it again.")


def sealed_files(run: Path) -> set[str]:
    """The names of the files `run`'s summary.json seals (none where it has no seal or cannot be read)."""
    try:
        summary = read_json(run / "summary.json")
    except (CheckpointError, OSError):
        return set()
    seal = summary.get(SEAL) if isinstance(summary, dict) else None
    return set(seal) if isinstance(seal, dict) else set()


def _sealing_sessions(summary: dict, run: Path) -> bool:
    """Whether a session of the summary's, or of `run`'s sessions.json, was trained by a pobax that seals (`SEALS`)."""
    def sealing(sessions: Any) -> bool:
        return isinstance(sessions, list) and any(isinstance(x, dict) and x.get(SEALS) is True for x in sessions)

    if sealing(summary.get("sessions")):
        return True
    try:
        return (run / "sessions.json").is_file() and sealing(read_json(run / "sessions.json"))
    except (CheckpointError, OSError):
        return False  # a sessions.json that does not read is its readers' to name


def check_config_of(summary: dict, run: Path) -> None:
    """A CheckpointError naming `run`'s config.json where it contradicts the summary: environment, agent, seeds and
    each set's hyperparameters. (A config.json that does not read as a configuration is its readers' to name.)"""
    from ..agent import config_from_dict  # noqa: PLC0415  (the agent package reads run directories' files too)
    from ..agent._config import NUMERIC  # noqa: PLC0415

    try:
        cfg = config_from_dict(read_json(run / "config.json")["config"])
        grid = cfg.grid()
    except Exception:  # noqa: BLE001
        return
    ours = {"env": cfg.env, "observability": cfg.observability, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "num_seeds": cfg.num_seeds}
    wrong = [k for k, v in ours.items() if k in summary and summary[k] != v]
    sets = summary.get("sets")
    if isinstance(sets, list) and len(sets) != len(grid):
        wrong.append(f"the number of hyperparameter sets, {len(grid)}")
    elif isinstance(sets, list):
        wrong += [f"set {i}'s {k}" for i, (row, hp) in enumerate(zip(sets, grid)) if isinstance(row, dict)
                  for k in NUMERIC if isinstance(row.get(k), int | float) and not math.isclose(row[k], hp[k],
                                                                                              rel_tol=1e-6)]
    if wrong:
        raise CheckpointError(f"{str(run / 'config.json')!r} does not match the run's finished summary.json ({wrong[0]} "
                              f"differs): the file was edited or damaged; restore it, or train the run again.")
