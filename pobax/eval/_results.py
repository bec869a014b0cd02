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
an unfinished run's metrics (plot, eval, load_run) checks the chunks' hashes likewise, and reading a finished run's
summary checks its seal: a summary, metrics table or model edited after the run finished is refused by name.
"""

import hashlib
import io
import json
import os
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import pandas as pd

from .._distributed import as_key_like, is_key
from ..agent import config_from_dict
from ._files import (CheckpointError, atomic_write_bytes, atomic_write_text, lock_dir,  # noqa: F401
                     check_seal, config_fields_differing, json_digest, nan_for_null, plain, read_json, read_or_none,
                     seal_summary, serialise, sha256_of, without_seal, writable_dir, write_json)
from ._metrics_table import ordered_metrics, read_metrics


class RunDirExistsError(FileExistsError):
    pass


class RunDirBusyError(CheckpointError):
    """A run directory that another process is training (`RunDir.hold`)."""


def _timed(chunk) -> bool:
    """A chunk's entry in sessions.json: its index, seconds and env steps."""
    return isinstance(chunk, dict) and all(isinstance(chunk.get(k), (int, float)) and not isinstance(chunk.get(k), bool)
                                           for k in ("chunk", "seconds", "env_steps"))


class RunDir:
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

    def write_chunk(self, index: int, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics" / f"{index:05d}.csv", df.to_csv(index=False))

    def metrics(self) -> pd.DataFrame:
        """The metrics table: `metrics.csv` if the run finished; else the chunks its checkpoint has trained, checked
        as a resume checks them (`verified_chunks`), or before its first checkpoint every chunk written so far."""
        full = self.path / "metrics.csv"
        if (self.path / "summary.json").exists():
            self.read_summary()  # finished: its seal checked (the configuration below, the metrics table)
        if not full.exists() and (self.path / "summary.json").exists():
            raise CheckpointError(f"{str(full)!r} is missing: the run finished (summary.json) with its metrics table "
                                  f"there; restore it (its chunks' files are not what it finished with).")
        if full.exists():
            df = read_metrics(full)
            cfg = config_from_dict(self.read_config()["config"], source=repr(str(self.path / "config.json")))
            runs = len(cfg.grid()) * cfg.num_seeds
            if len(df) != runs * cfg.num_updates or df[["hp_index", "seed", "update"]].isna().any(axis=None):
                raise CheckpointError(f"{str(full)!r} holds {len(df):,} rows, not one per update of each of the run's "
                                      f"{runs} runs ({cfg.num_updates:,} updates each): the file is damaged (cut "
                                      f"short or edited); restore it.")
            return df
        if (self.path / "checkpoint.json").exists():
            return self.chunk_metrics(self.verified_chunks())
        chunks = sorted((self.path / "metrics").glob("[0-9]*.csv"))
        if not chunks:
            raise FileNotFoundError(f"No metrics in {str(self.path)!r}: is it a pobax run directory?")
        return pd.concat([read_metrics(c) for c in chunks], ignore_index=True)

    def chunk_metrics(self, count: int) -> pd.DataFrame:
        """The metrics of the first `count` chunks as one table, in `metrics.csv`'s order (set, seed, update)."""
        return ordered_metrics(self.chunks(count))

    def write_metrics(self, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics.csv", df.to_csv(index=False))

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

    def chunks(self, count: int) -> list[pd.DataFrame]:
        """The metrics of chunks 0 … count - 1."""
        paths = [self.path / "metrics" / f"{c:05d}.csv" for c in range(count)]
        missing = [p.name for p in paths if not p.exists()]
        if missing:
            raise CheckpointError(f"The checkpoint in {str(self.path)!r} is past the metrics written (missing "
                                  f"metrics/{missing[0]}): the run directory is damaged; start a new run.")
        return [read_metrics(p) for p in paths]

    def save_checkpoint(self, state, chunks_done: int, num_chunks: int, config: dict) -> None:
        """The whole training state after `chunks_done` chunks, as one unit (see the module docstring). The manifest
        (checkpoint.json) also holds the configuration the run trains (`config`, as config.json's "config") and the
        SHA-256 of every chunk's metrics file: what the resumed run builds on, checked when it starts."""
        data = serialise(key_data(state))
        name = f"checkpoint-{chunks_done:05d}.eqx"
        atomic_write_bytes(self.path / name, data)
        chunks = [sha256_of(self.path / "metrics" / f"{c:05d}.csv") for c in range(chunks_done)]
        manifest = {"chunks_done": chunks_done, "num_chunks": num_chunks, "file": name,
                    "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data), "config": config,
                    "metrics_sha256": chunks}
        write_json(self.path / "checkpoint.json", {**manifest, "manifest_sha256": json_digest(manifest)})
        for old in self.path.glob("checkpoint-*.eqx"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def load_checkpoint(self, like) -> tuple[Any, int]:
        """(state, chunks done) of the checkpoint `checkpoint.json` names, checked against its hash and against
        `like` (a state or its shapes). Raises CheckpointError with what to do."""
        data, done, path = self.checkpoint_bytes()
        try:
            stored = eqx.tree_deserialise_leaves(io.BytesIO(data), key_data(like))
        except Exception as e:  # noqa: BLE001  (wrong shapes: another configuration or device layout)
            raise CheckpointError(f"Checkpoint {str(path)!r} does not match this run ({e}).") from None
        return jax.tree.map(lambda x, ref: as_key_like(x, ref) if is_key(ref) else x, stored, like), done

    def manifest(self) -> dict:
        """checkpoint.json, checked: written by pobax and unedited (its own SHA-256), consistent (the chunks done, the
        state's file name and the metrics' hashes agree). Raises CheckpointError naming what is wrong."""
        where = str(self.path)
        try:
            m = json.loads(plain(self.path / "checkpoint.json").read_text())
            done, name, _ = int(m["chunks_done"]), str(m["file"]), str(m["sha256"])
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError):
            raise CheckpointError(f"{where}/checkpoint.json is not a checkpoint manifest pobax wrote (unreadable or "
                                  f"from an older version); start a new run.") from None
        body = {k: v for k, v in m.items() if k != "manifest_sha256"}
        chunks = m.get("metrics_sha256")
        if m.get("manifest_sha256") != json_digest(body) or not isinstance(chunks, list) \
                or len(chunks) != done or name != f"checkpoint-{done:05d}.eqx":
            raise CheckpointError(f"{where}/checkpoint.json was edited (its own SHA-256, its chunks' hashes or its "
                                  f"chunk count missing or not matching): the run cannot be resumed exactly; restore it "
                                  f"or start a new run.")
        return m

    def checkpoint_bytes(self) -> tuple[bytes, int, Path]:
        """(the serialised state, chunks done, its path) of the checkpoint `checkpoint.json` names, checked against
        its hash, and every chunk's metrics file it builds on against theirs: what a resume checks before it compiles
        anything. A reader beside the process that trains the run (`eval`, `plot`, `results`) can see the checkpoint
        replaced and the one it read deleted: a check that fails while checkpoint.json changed is made again (a run
        being trained is not damaged); one that fails on an unchanged manifest is damage."""
        meta = self.path / "checkpoint.json"
        for _ in range(CHECKPOINT_READS - 1):
            before = read_or_none(meta)
            try:
                return self._checkpoint_bytes_once()
            except CheckpointError:
                if read_or_none(meta) == before:
                    raise
        return self._checkpoint_bytes_once()

    def _checkpoint_bytes_once(self) -> tuple[bytes, int, Path]:
        where = str(self.path)
        meta = self.path / "checkpoint.json"
        if not meta.exists():
            raise CheckpointError(f"No checkpoint in {where!r} (no checkpoint.json): the run stopped before its first "
                                  f"checkpoint or finished (see summary.json); start it again with another --out.")
        m = self.manifest()
        done, name = int(m["chunks_done"]), str(m["file"])
        path = self.path / name
        try:
            data = plain(path).read_bytes() if path.parent == self.path else None
        except OSError:  # missing, or deleted since checkpoint.json was read (a newer checkpoint replaced it)
            data = None
        if data is None or hashlib.sha256(data).hexdigest() != str(m["sha256"]):
            raise CheckpointError(f"Checkpoint {str(path)!r} is missing or corrupted (its SHA-256 does not match "
                                  f"checkpoint.json); the run cannot be resumed exactly: start a new run.")
        self._check_chunks(m)
        return data, done, path

    def verified_chunks(self) -> int:
        """The chunks done by the checkpoint that checkpoint.json names (`manifest`), every chunk's metrics file it
        builds on checked against the SHA-256 it recorded (as a resume checks them): what the metrics of an unfinished
        run are read from. Raises CheckpointError naming a file missing or damaged."""
        m = self.manifest()
        self._check_chunks(m)
        return int(m["chunks_done"])

    def _check_chunks(self, m: dict) -> None:
        """Every chunk's metrics file that the manifest `m` builds on is there, with the SHA-256 it recorded."""
        done = int(m["chunks_done"])
        for c, want in enumerate(m["metrics_sha256"][:done]):
            chunk = self.path / "metrics" / f"{c:05d}.csv"
            if not chunk.exists():
                raise CheckpointError(f"The checkpoint in {str(self.path)!r} is past the metrics written (missing "
                                      f"metrics/{chunk.name}): the run directory is damaged; start a new run.")
            if sha256_of(chunk) != want:
                raise CheckpointError(f"{str(chunk)!r} is damaged (its SHA-256 differs from the one checkpoint.json "
                                      f"recorded): its metrics cannot be read, nor the run resumed exactly; restore "
                                      f"it or start a new run.")

    def clear_checkpoint(self) -> None:
        (self.path / "checkpoint.json").unlink(missing_ok=True)
        for p in self.path.glob("checkpoint-*.eqx"):
            p.unlink(missing_ok=True)

    def remove_stray_temporaries(self) -> None:
        """Temporary files left by a process killed in the middle of a write."""
        for p in [*self.path.glob(".*.tmp"), *self.path.glob("metrics/.*.tmp")]:
            p.unlink(missing_ok=True)


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


def key_data(state):
    """Typed PRNG keys as their raw key data (what a checkpoint stores); shapes of keys as shapes of their data."""
    def raw(x):
        if not is_key(x):
            return x
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.eval_shape(jax.random.key_data, x)
        return jax.random.key_data(x)

    return jax.tree.map(raw, state)


#: How many times `RunDir.checkpoint_bytes` reads a checkpoint that changes while it is read (a run being trained
#: writes one a chunk, seconds to hours apart) before it reports the failure.
CHECKPOINT_READS = 20

#: How many times `RunDir.hold` tries the lock, 50 ms apart, before it says another process trains the run.
HOLD_TRIES = 10
