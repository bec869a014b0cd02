"""Run directories: resolved config, tidy metrics table, checkpoints, model parameters, summary.

Layout of a run directory:

    config.json         the resolved configuration (and the hyperparameter sets, by index), device, JAX, commit
    metrics/NNNNN.csv   one file per chunk of updates, written as they come
    checkpoint.json     while a run is unfinished: the chunks done, the checkpoint file's name and SHA-256, the
                        configuration trained, each chunk's metrics' SHA-256, and the manifest's own SHA-256
    checkpoint-NNNNN.eqx  the whole training state after chunk NNNNN (the one checkpoint.json names)
    metrics.csv         all chunks, ordered by (hyperparameter set, seed, update): deterministic columns only
    sessions.json       every process that trained here (a first start, then each resume): when, from which chunk,
                        on which device, JAX and commit, and each chunk's seconds and env steps (not deterministic)
    timing.csv          seconds and env steps of every chunk, with the session that trained it (not deterministic)
    model.eqx           final parameters of every run (hyperparameter set × seed), `eqx.tree_serialise_leaves`
    obs_norm.eqx        with normalised observations: every run's final observation statistics
    summary.json        final returns per hyperparameter set: mean and 95% CI over seeds (null where none), diverged
                        runs; written last, sealed with its own SHA-256 and metrics.csv's, model.eqx's, obs_norm.eqx's

Every file is written to a temporary name in the same directory and then renamed, so an interrupted run never
leaves a half-written file, and nothing already written is overwritten by a new run. A checkpoint is one unit: its
state is written under a new name, then checkpoint.json (naming it, with its hash) replaces the previous one, then
older states are removed; a resume reads only what checkpoint.json names and checks its hash, the hashes of the
chunks' metrics it builds on, and that the configuration in config.json is the one the run started with. Reading
an unfinished run (plot, eval, load_run, results) checks what a resume checks (`RunDir.check_unfinished`), and
reading a finished run's summary checks its seal: a summary, metrics table or model edited after the run finished is
refused by name. The seals are SHA-256s without a key: they catch edits and damage, not a forger who writes them
again (or who removes a seal together with every record that the run's pobax seals, as a run from before seals reads).
"""

import dataclasses
import json
import os
import re
import time
from pathlib import Path
from typing import Any

import equinox as eqx

from .._paths import shell_word
from ..agent import TrainConfig
from ..agent._config import saved_config_differences
from ._files import (CheckpointError, atomic_write_bytes, atomic_write_text,  # noqa: F401
                     config_fields_differing, nan_for_null, plain, read_json, serialise, writable_dir, write_json)
from ._locks import lock_dir
from ._seal import check_seal, seal_summary, without_seal
from ._checkpoint import Checkpoints
from ._run_metrics import RunMetrics


class RunDirExistsError(FileExistsError):
    pass


class RunDirBusyError(CheckpointError):
    """A run directory that another process is training (`RunDir.hold`)."""


class RunFinishedError(CheckpointError):
    """A resume of a run that has finished (its summary.json): nothing to resume."""


class RunDirMovedError(CheckpointError):
    """A run directory moved, removed or replaced while this process trained it (`RunDir.check_in_place`)."""


def _timed(chunk) -> bool:
    """A chunk's entry in sessions.json: its index, seconds and env steps."""
    return isinstance(chunk, dict) and all(isinstance(chunk.get(k), (int, float)) and not isinstance(chunk.get(k), bool)
                                           for k in ("chunk", "seconds", "env_steps"))


class RunDir(RunMetrics, Checkpoints):
    """A run directory (the layout above): its configuration, metrics, sessions, model and summary; its
    checkpoints come from `Checkpoints`."""

    """A run directory (see the module docstring)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._held = None  # the open directory whose lock `hold` took

    @classmethod
    def create(cls, path: str | os.PathLike, config: dict) -> "RunDir":
        """Create a new run directory, take it (`hold`) and write its config.json (`config`). Refuses a directory
        another process holds, and one that holds anything but what a run stopped before its first chunk leaves (its
        config.json, which must then be this configuration's): results are never overwritten. Checked before anything
        is written (a refused directory stays as it was) and again under the lock, so two processes given the same
        new directory cannot both pass."""
        p = Path(path)
        _check_free(p, config)
        try:
            p.mkdir(parents=True, exist_ok=True)
            writable_dir(p)
        except OSError as e:
            why = e.strerror or e
            if p.is_symlink() and not p.exists():  # (mkdir's "File exists" would not say why)
                why = f"a symbolic link to {os.readlink(p)!r}, which does not exist or leads back to itself"
            raise RunDirExistsError(f"Cannot write the run directory {str(p)!r} ({why}); pass another --out.") from None
        run_dir = cls(p)
        run_dir.hold()
        try:
            _check_free(p, config, held=True)
            (p / "metrics").mkdir(exist_ok=True)
            for q in [*p.glob(".*.tmp"), *p.glob("metrics/.*.tmp")]:  # a write cut by a kill
                q.unlink(missing_ok=True)
            run_dir.write_config(config)
        except BaseException:
            run_dir.release()
            raise
        return run_dir

    def write_config(self, config: dict) -> None:
        write_json(self.path / "config.json", config)

    def hold(self) -> None:
        """Take the run directory for this process's training until `release`: a second process (the same --out given
        twice, a benchmark started again while an earlier one's job still trains, a resume run twice) is refused
        instead of writing the same checkpoints and metrics. An advisory lock (`flock`, where the system has it) on
        the directory itself (`lock_dir`: no file in it can be deleted to take the lock away); the system drops it
        when the process ends, however it ends."""
        for attempt in range(HOLD_TRIES):  # (a reader probing the lock, `pobax results`, holds it for an instant)
            try:
                self._held = lock_dir(self.path, wait=False)  # held open until `release`; None: unguarded
                return
            except BlockingIOError:
                if attempt < HOLD_TRIES - 1:
                    time.sleep(0.05)
        raise RunDirBusyError(f"The run in {str(self.path)!r} is being trained by another process; wait for it to end, "
                              f"or pass another --out.")

    def held_elsewhere(self) -> bool:
        """Whether another process holds the run directory (`hold`: it trains it). Probed by taking the lock and
        dropping it at once; a process starting to train it in that instant waits for it (`hold` tries again)."""
        try:
            opened = lock_dir(self.path, wait=False)
        except BlockingIOError:
            return True
        except OSError:
            return False
        if opened is not None:
            opened.close()
        return False

    def in_place(self) -> bool:
        """Whether the directory this process holds (`hold`) is still the one at its path (True without the lock)."""
        if self._held is None or self._held.fd is None:
            return True
        held = os.fstat(self._held.fd)
        try:
            now = os.stat(self.path)
        except OSError:
            return False
        return (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino)

    def check_in_place(self) -> None:
        """Raise RunDirMovedError where the directory this process holds (`hold`) is no longer at its path: moved,
        removed or replaced by another while training. Writing on by the path would start a second, broken run there
        (chunks without their configuration) while the moved one stops short, so training stops instead and says where
        the run is now (where the system tells: `/proc/self/fd`) and how to continue it. Nothing to check without the
        lock (a file system without `flock`)."""
        if self.in_place():
            return
        where = _path_of(self._held.fd)
        if os.fstat(self._held.fd).st_nlink == 0:
            raise RunDirMovedError(f"The run directory {str(self.path)!r} was removed while training, so training "
                                   f"stopped; its results are gone: train it again.")
        there = (f"it is now {where!r}: continue it with `pobax train --resume {shell_word(where)}`" if where else
                 "continue it with `pobax train --resume` on its new path")
        raise RunDirMovedError(f"The run directory {str(self.path)!r} was moved or replaced while training, so training "
                               f"stopped and wrote nothing at its old path; {there}.")

    def release(self) -> None:
        """End `hold` (closing the file drops the lock)."""
        handle, self._held = self._held, None
        if handle is not None:
            handle.close()

    def discard(self) -> None:
        """Remove what `create` wrote (a run that failed before its first chunk: nothing of it is worth keeping), and
        the directory once empty; anything else in it stays."""
        for name in ("config.json", "sessions.json"):
            (self.path / name).unlink(missing_ok=True)
        for d in (self.path / "metrics", self.path):
            try:
                d.rmdir()
            except OSError:
                pass

    def read_config(self) -> dict:
        """config.json; a CheckpointError naming it where it is not one pobax wrote (an object holding the
        configuration as an object)."""
        path = self.path / "config.json"
        record = read_json(path)
        if not (isinstance(record, dict) and isinstance(record.get("config"), dict)):
            raise CheckpointError(f"{str(path)!r} is not a run configuration pobax wrote (no 'config' object): the "
                                  f"file is damaged; restore it.")
        return record

    def sessions(self, before: int | None = None) -> list[dict]:
        """The processes that trained here so far (`sessions.json`; empty before the first chunk). With `before` (the
        checkpoint's chunks done): the sessions that trained chunks 0 … before - 1, each with only those chunks, which
        must all be there, timed; else the file is damaged (CheckpointError naming it)."""
        path = self.path / "sessions.json"
        sessions = read_json(path) if path.exists() else []
        if before is None:
            return sessions
        kept = None
        if isinstance(sessions, list) and all(isinstance(x, dict) and isinstance(x.get("chunks"), list)
                                              and all(map(_timed, x["chunks"])) for x in sessions):
            kept = [dict(x, chunks=[c for c in x["chunks"] if c["chunk"] < before]) for x in sessions]
        if kept is None or before > 0 and sorted(c["chunk"] for x in kept for c in x["chunks"]) != list(range(before)):
            raise CheckpointError(f"{str(path)!r} does not record the sessions that trained chunks 0 … {before - 1} "
                                  f"(missing or edited): the run directory is damaged; restore it, or start a new run.")
        return [x for x in kept if x["chunks"]]

    def write_sessions(self, sessions: list[dict]) -> None:
        write_json(self.path / "sessions.json", sessions)

    def check_unfinished(self) -> None:
        """What a resume checks of a run without summary.json before it compiles, but for what depends on the
        resuming process (its configuration and environment, a writable directory): no trained file (metrics.csv,
        model.eqx, a chunk after the first) without checkpoint.json; the checkpoint and every chunk it builds on
        (their SHA-256s); sessions.json; config.json against the configuration the checkpoint was trained with.
        Readers check it too (`load_run`, `metrics`, `pobax results`), so that a run they read is one a resume
        continues. Raises CheckpointError naming the file."""
        where = str(self.path)
        if not (self.path / "checkpoint.json").exists():
            # chunk k > 0 trains only after the checkpoint of chunk k - 1; a finished run's files come with its summary
            trained = [p.name for p in (self.path / "metrics.csv", self.path / "model.eqx") if p.exists()] + \
                [f"metrics/{p.name}" for p in sorted((self.path / "metrics").glob("*.csv")) if p.stem.isdigit()
                 and int(p.stem) > 0]
            if trained:
                raise CheckpointError(f"The run in {where!r} has trained past a checkpoint ({', '.join(trained[:3])}) "
                                      f"but has no checkpoint.json (nor summary.json): restore it, or start a new run "
                                      f"with another --out.")
            return
        self.checkpoint_bytes()  # the state's and the chunks' hashes, made again if a training process replaced them
        m = self.manifest()
        self.sessions(before=m["chunks_done"])  # sessions.json is written before the checkpoint that counts a chunk
        started, now = m.get("config"), self.read_config()["config"]
        diff = [] if started is None else saved_config_differences(started, now)
        if diff:
            defaults = dataclasses.asdict(TrainConfig())
            value = lambda d, k: json.dumps(d.get(k, defaults[k]), default=str)  # noqa: E731
            raise CheckpointError(
                f"{where}/config.json differs from the configuration the run started with in {', '.join(diff)} ("
                + ", ".join(f"{value(started, k)} → {value(now, k)}" for k in diff[:3])
                + "): a resume trains on exactly as it began; restore config.json, or start a new run with another "
                  "--out.")

    def save_model(self, model: eqx.Module, obs_norm: eqx.Module | None = None) -> None:
        """The final parameters of every run, and their observation statistics when they normalised observations."""
        atomic_write_bytes(self.path / "model.eqx", serialise(model))
        if obs_norm is not None:
            atomic_write_bytes(self.path / "obs_norm.eqx", serialise(obs_norm))

    def load_model(self, like: eqx.Module | None = None) -> eqx.Module:
        """The final parameters of every run (stacked), read into `like` (their shapes). `pobax.load_run` builds
        `like` from the run's configuration and gives the model with everything else."""
        path = self.path / "model.eqx"
        if not path.exists():
            raise FileNotFoundError(f"No model in {str(self.path)!r} (expected {str(path)!r}).")
        if like is None:
            raise TypeError("RunDir.load_model needs the model's shapes (`like`); pobax.load_run(path).model builds "
                            "them from the run's configuration.")
        return eqx.tree_deserialise_leaves(plain(path), like)

    def write_summary(self, summary: dict) -> None:
        """summary.json, sealed (`seal_summary`): written last, after the files its seal holds."""
        write_json(self.path / "summary.json", seal_summary(summary, self.path))

    def read_summary(self) -> Any:
        """summary.json as written, its seal checked (`check_seal`; callers check its shape: `check_part_summary`)."""
        summary = read_json(self.path / "summary.json")
        check_seal(summary, self.path)
        return nan_for_null(without_seal(summary))

    def remove_stray_temporaries(self) -> None:
        """Temporary files left by a trainer killed in the middle of a write (`stray_temporaries`)."""
        for p in stray_temporaries(self.path):
            p.unlink(missing_ok=True)


#: The temporary name (`_new_temporary`) of a file that training writes into a run directory: `.NAME.<random>.tmp`.
_TRAINER_TEMPORARY = re.compile(r"\.(config\.json|sessions\.json|checkpoint\.json|checkpoint-\d+\.eqx|metrics\.csv|"
                                r"timing\.csv|model\.eqx|obs_norm\.eqx|summary\.json)\.[0-9a-z]+\.tmp")
_CHUNK_TEMPORARY = re.compile(r"\.\d+\.csv\.[0-9a-z]+\.tmp")


def stray_temporaries(path: Path) -> list[Path]:
    """The temporaries of training's own files in the run directory `path` (and its metrics/): what a trainer killed
    in the middle of a write leaves, which the trainer holding the run (`RunDir.hold`) removes. Not another command's
    temporaries there: an `eval`, `plot` or `render` writing its output into the run directory at that moment
    (`atomic_write_bytes`, `writable_dir`) would find its file gone."""
    return [*(q for q in Path(path).glob(".*.tmp") if _TRAINER_TEMPORARY.fullmatch(q.name)),
            *(q for q in Path(path).glob("metrics/.*.tmp") if _CHUNK_TEMPORARY.fullmatch(q.name))]


def _check_free(p: Path, config: dict, held: bool = False) -> None:
    """Raise RunDirExistsError unless `p` can become the run directory of `config` (`RunDir.create`); RunDirBusyError
    where another process holds it (unless this one does: `held`)."""
    if p.exists() and not p.is_dir():
        raise RunDirExistsError(f"--out {str(p)!r} is a file; pass a directory for the run.")
    if not p.is_dir():
        return
    if not held:  # another process may be training it: say so, whatever else it holds
        probe = RunDir(p)
        probe.hold()
        probe.release()
    stray = [*p.glob(".*.tmp"), *p.glob("metrics/.*.tmp")]  # a write cut by a kill
    left = [q for q in p.rglob("*") if not q.is_dir() and q not in stray and q != p / "config.json"]
    if left:
        unfinished = (p / "config.json").exists() and not (p / "summary.json").exists()
        hint = f" (an unfinished run: continue it with pobax train --resume {str(p)})" if unfinished else ""
        raise RunDirExistsError(f"Run directory {str(p)!r} already exists and is not empty{hint}; pass another --out, "
                                f"or remove it if you no longer need its results.")
    if (p / "config.json").exists():
        if not _is_run_config(p / "config.json"):
            raise RunDirExistsError(f"--out {str(p)!r} holds a config.json that is not a pobax run's; pass another "
                                    f"--out.")
        diff = config_fields_differing(read_json(p / "config.json")["config"], config.get("config", {}))
        if diff:
            raise RunDirExistsError(f"--out {str(p)!r} holds the config.json of a run with another configuration "
                                    f"(differs in: {', '.join(diff)}) that stopped before its first chunk; pass "
                                    f"another --out, or remove it.")


def _is_run_config(path: Path) -> bool:
    """Whether `path` is a run's config.json (what `train` writes first)."""
    try:
        return "hyperparameter_sets" in RunDir(path.parent).read_config()
    except (CheckpointError, OSError):
        return False


#: How many times `RunDir.hold` tries the lock, 50 ms apart, before it says another process trains the run.
HOLD_TRIES = 10


def _path_of(fd: int) -> str | None:
    """The path of the open directory `fd` now, where the system says (Linux's `/proc/self/fd`); None where it does
    not, or where the directory was removed."""
    try:
        where = os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return None
    return None if where.endswith(" (deleted)") or not os.path.isdir(where) else where
