"""Run directories: resolved config, tidy metrics table, checkpoints, model parameters, summary.

Layout of a run directory:

    config.json         the resolved configuration (and the hyperparameter sets, by index), device, JAX, commit
    metrics/NNNNN.csv   one file per chunk of updates, written as they come
    checkpoint.json     while a run is unfinished: the chunks done, the checkpoint file's name and SHA-256
    checkpoint-NNNNN.eqx  the whole training state after chunk NNNNN (the one checkpoint.json names)
    metrics.csv         all chunks, ordered by (hyperparameter set, seed, update): deterministic columns only
    sessions.json       every process that trained here (a first start, then each resume): when, from which chunk,
                        on which device, JAX and commit, and each chunk's seconds and env steps (not deterministic)
    timing.csv          seconds and env steps of every chunk, with the session that trained it (not deterministic)
    model.eqx           final parameters of every run (hyperparameter set × seed), `eqx.tree_serialise_leaves`
    obs_norm.eqx        with normalised observations: every run's final observation statistics
    summary.json        final returns per hyperparameter set: mean and 95% CI over seeds, diverged runs

Every file is written to a temporary name in the same directory and then renamed, so an interrupted run never
leaves a half-written file, and nothing already written is overwritten by a new run. A checkpoint is one unit: its
state is written under a new name, then checkpoint.json (naming it, with its hash) replaces the previous one, then
older states are removed; a resume reads only what checkpoint.json names and checks its hash.
"""

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import pandas as pd

class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed (missing, corrupted, or from another configuration)."""


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _new_temporary(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _new_temporary(path: Path) -> tuple[int, str]:
    """A new file `.<name>.<random>.tmp` beside `path`, opened for writing, created with mode 0666 as `open` creates
    files, so that the umask in force now (and a default ACL) decides its permissions (`mkstemp` makes 0600)."""
    while True:
        tmp = str(path.parent / f".{path.name}.{os.urandom(6).hex()}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp
        except FileExistsError:
            continue


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n")


class RunDirExistsError(FileExistsError):
    pass


class RunDirBusyError(CheckpointError):
    """A run directory that another process is training (`RunDir.hold`)."""


class RunDir:
    """A run directory (see the module docstring)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._held = None  # the open config.json whose lock `hold` took

    @classmethod
    def create(cls, path: str | os.PathLike) -> "RunDir":
        """Create a new run directory. Refuses a directory that holds anything but what a run stopped before its first
        chunk leaves (its config.json): results are never overwritten."""
        p = Path(path)
        if p.exists() and not p.is_dir():
            raise RunDirExistsError(f"--out {str(p)!r} is a file; pass a directory for the run.")
        stray = [*p.glob(".*.tmp"), *p.glob("metrics/.*.tmp")] if p.is_dir() else []  # a write cut by a kill
        left = [q for q in p.rglob("*") if not q.is_dir() and q not in stray and q != p / "config.json"] \
            if p.is_dir() else []
        if left:
            unfinished = (p / "config.json").exists() and not (p / "summary.json").exists()
            hint = f" (an unfinished run: continue it with pobax train --resume {str(p)})" if unfinished else ""
            raise RunDirExistsError(
                f"Run directory {str(p)!r} already exists and is not empty{hint}; pass another --out, or remove it "
                f"if you no longer need its results."
            )
        if (p / "config.json").exists() and not _is_run_config(p / "config.json"):
            raise RunDirExistsError(f"--out {str(p)!r} holds a config.json that is not a pobax run's; pass another "
                                    f"--out.")
        try:
            (p / "metrics").mkdir(parents=True, exist_ok=True)
            writable_dir(p)
            for q in stray:
                q.unlink(missing_ok=True)
        except OSError as e:
            raise RunDirExistsError(f"Cannot write the run directory {str(p)!r} ({e.strerror or e}); pass another "
                                    f"--out.") from None
        return cls(p)

    def write_config(self, config: dict) -> None:
        write_json(self.path / "config.json", config)

    def hold(self) -> None:
        """Take the run directory for this process's training until `release`: a second process (a benchmark
        started again while an earlier one's job still trains, a resume run twice) is refused instead of writing
        the same checkpoints and metrics. An advisory lock on config.json (`flock`, where the system has it), which
        the system drops when the process ends, however it ends."""
        try:
            import fcntl  # noqa: PLC0415  (POSIX only)
        except ImportError:
            return
        handle = open(self.path / "config.json", "rb")  # noqa: SIM115  (held open until `release`)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            raise RunDirBusyError(f"The run in {str(self.path)!r} is being trained by another process; wait for it "
                                  f"to end, or pass another --out.") from None
        except OSError:  # a file system without locks: train unguarded, as before
            handle.close()
            return
        self._held = handle

    def release(self) -> None:
        """End `hold` (closing the file drops the lock)."""
        handle, self._held = self._held, None
        if handle is not None:
            handle.close()

    def read_config(self) -> dict:
        return read_json(self.path / "config.json")

    def sessions(self) -> list[dict]:
        """The processes that trained here so far (`sessions.json`; empty before the first chunk)."""
        path = self.path / "sessions.json"
        return read_json(path) if path.exists() else []

    def write_sessions(self, sessions: list[dict]) -> None:
        write_json(self.path / "sessions.json", sessions)

    def write_chunk(self, index: int, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics" / f"{index:05d}.csv", df.to_csv(index=False))

    def metrics(self) -> pd.DataFrame:
        """The metrics table: `metrics.csv` if the run finished, else every chunk written so far."""
        full = self.path / "metrics.csv"
        if full.exists():
            return pd.read_csv(full)
        chunks = sorted((self.path / "metrics").glob("[0-9]*.csv"))
        if not chunks:
            raise FileNotFoundError(f"No metrics in {str(self.path)!r}: is it a pobax run directory?")
        return pd.concat([pd.read_csv(c) for c in chunks], ignore_index=True)

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
        return eqx.tree_deserialise_leaves(path, like)

    def write_summary(self, summary: dict) -> None:
        write_json(self.path / "summary.json", summary)

    def read_summary(self) -> dict:
        return read_json(self.path / "summary.json")

    def chunks(self, count: int) -> list[pd.DataFrame]:
        """The metrics of chunks 0 … count - 1."""
        paths = [self.path / "metrics" / f"{c:05d}.csv" for c in range(count)]
        missing = [p.name for p in paths if not p.exists()]
        if missing:
            raise CheckpointError(f"The checkpoint in {str(self.path)!r} is past the metrics written (missing "
                                  f"metrics/{missing[0]}): the run directory is damaged; start a new run.")
        return [pd.read_csv(p) for p in paths]

    def save_checkpoint(self, state, chunks_done: int, num_chunks: int) -> None:
        """The whole training state after `chunks_done` chunks, as one unit (see the module docstring)."""
        data = serialise(_storable(state))
        name = f"checkpoint-{chunks_done:05d}.eqx"
        atomic_write_bytes(self.path / name, data)
        write_json(self.path / "checkpoint.json", {"chunks_done": chunks_done, "num_chunks": num_chunks, "file": name,
                                                  "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)})
        for old in self.path.glob("checkpoint-*.eqx"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def load_checkpoint(self, like) -> tuple[Any, int]:
        """(state, chunks done) of the checkpoint `checkpoint.json` names, checked against its hash and against
        `like` (a state or its shapes). Raises CheckpointError with what to do."""
        data, done, path = self.checkpoint_bytes()
        try:
            stored = eqx.tree_deserialise_leaves(io.BytesIO(data), _storable(like))
        except Exception as e:  # noqa: BLE001  (wrong shapes: another configuration or device layout)
            raise CheckpointError(f"Checkpoint {str(path)!r} does not match this run ({e}).") from None
        return jax.tree.map(lambda x, ref: _wrap_key(x, ref) if _is_key(ref) else x, stored, like), done

    def checkpoint_bytes(self) -> tuple[bytes, int, Path]:
        """(the serialised state, chunks done, its path) of the checkpoint `checkpoint.json` names, checked against
        its hash (and the chunks' metrics against the count): what a resume checks before it compiles anything."""
        where = str(self.path)
        meta = self.path / "checkpoint.json"
        if not meta.exists():
            raise CheckpointError(f"No checkpoint in {where!r} (no checkpoint.json): the run stopped before its first "
                                  f"checkpoint or finished (see summary.json); start it again with another --out.")
        try:
            m = json.loads(meta.read_text())
            done, name, digest = int(m["chunks_done"]), str(m["file"]), str(m["sha256"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            raise CheckpointError(f"{where}/checkpoint.json is not a checkpoint manifest pobax wrote (unreadable or "
                                  f"from an older version); start a new run.") from None
        path = self.path / name
        data = path.read_bytes() if path.is_file() and path.parent == self.path else None
        if data is None or hashlib.sha256(data).hexdigest() != digest:
            raise CheckpointError(f"Checkpoint {str(path)!r} is missing or corrupted (its SHA-256 does not match "
                                  f"checkpoint.json); the run cannot be resumed exactly: start a new run.")
        missing = [c for c in range(done) if not (self.path / "metrics" / f"{c:05d}.csv").exists()]
        if missing:
            raise CheckpointError(f"The checkpoint in {where!r} is past the metrics written (missing "
                                  f"metrics/{missing[0]:05d}.csv): the run directory is damaged; start a new run.")
        return data, done, path

    def clear_checkpoint(self) -> None:
        (self.path / "checkpoint.json").unlink(missing_ok=True)
        for p in self.path.glob("checkpoint-*.eqx"):
            p.unlink(missing_ok=True)

    def remove_stray_temporaries(self) -> None:
        """Temporary files left by a process killed in the middle of a write."""
        for p in [*self.path.glob(".*.tmp"), *self.path.glob("metrics/.*.tmp")]:
            p.unlink(missing_ok=True)


class OutputDirError(ValueError):
    """An output directory that holds something this command did not write."""


def claim_out(out: Path, marker: str, owner: dict, reuse: bool = True) -> None:
    """Make `out` this command's output directory: new or empty, or (with `reuse`) one whose `marker` file says that
    an earlier call of the same command (`owner`, e.g. {"command": "gap", "env": ...}) wrote it. Writes the marker.
    Raises OutputDirError otherwise, before anything is written."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputDirError(f"--out {str(out)!r} is a file; pass a directory.")
    mark = out / marker
    if out.is_dir() and any(out.iterdir()):
        mine = mark.exists() and {k: read_json(mark).get(k) for k in owner} == owner
        if not (reuse and mine):
            what = "another call's results" if mark.exists() else "files this command did not write"
            raise OutputDirError(f"--out {str(out)!r} holds {what}; pass a new or empty directory"
                                 + (" (or the --out of an earlier call with the same settings to continue it)."
                                    if reuse else "."))
    try:
        out.mkdir(parents=True, exist_ok=True)
        writable_dir(out)
    except OSError as e:
        raise OutputDirError(f"Cannot write --out {str(out)!r} ({e.strerror or e}); pass another directory.") from None
    if not mark.exists():
        write_json(mark, owner)


def ordered_metrics(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Chunks' metrics as one table ordered by hyperparameter set, seed and update (`metrics.csv`'s order)."""
    return pd.concat(frames, ignore_index=True).sort_values(["hp_index", "seed", "update"], ignore_index=True)


def read_json(path: str | os.PathLike) -> Any:
    """A JSON file that pobax wrote; a one-line CheckpointError that names it where it is not valid JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{str(path)!r} is not valid JSON ({e}); the file is damaged: restore it, or pass "
                              f"another directory.") from None


def _is_run_config(path: Path) -> bool:
    """Whether `path` is a run's config.json (what `train` writes first)."""
    try:
        record = read_json(path)
    except (CheckpointError, OSError):
        return False
    return isinstance(record, dict) and isinstance(record.get("config"), dict) and "hyperparameter_sets" in record


def writable_dir(path: Path) -> None:
    """Raise OSError unless a file can be created in the directory `path` (checked by creating one)."""
    fd, tmp = tempfile.mkstemp(dir=path, prefix=".write-check.", suffix=".tmp")
    os.close(fd)
    os.unlink(tmp)


def serialise(tree) -> bytes:
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, jax.device_get(tree))
    return buf.getvalue()


def _is_key(x) -> bool:
    dtype = getattr(x, "dtype", None)
    return dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def _wrap_key(data, like):
    """Raw key data as a typed key like `like` (a key array, or a shape of one: then the default implementation, which
    made the keys, `jax.random.key(seed)`)."""
    impl = None if isinstance(like, jax.ShapeDtypeStruct) else jax.random.key_impl(like)
    return jax.random.wrap_key_data(data, impl=impl)


def _storable(state):
    """Typed PRNG keys as their raw key data (what a checkpoint stores)."""
    def raw(x):
        if not _is_key(x):
            return x
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.eval_shape(jax.random.key_data, x)
        return jax.random.key_data(x)

    return jax.tree.map(raw, state)


def list_runs(root: str | os.PathLike) -> list[dict]:
    """Every run directory under `root` (a directory with config.json and metrics): its environment, agent,
    number of hyperparameter sets and seeds, state (finished / resumable / incomplete / damaged) and, when finished, the
    final discounted return of its best set by AUC (mean and 95% CI over seeds)."""
    rows = []
    for cfg_path in sorted(Path(root).rglob("config.json")):
        rd = RunDir(cfg_path.parent)
        if not _is_run_config(cfg_path):  # another program's config.json, or a damaged one
            continue
        record = rd.read_config()
        cfg = record["config"]
        row = {"path": str(rd.path), "env": cfg.get("env", "?"), "observability": cfg.get("observability", "?"),
               "agent": cfg.get("memory", "?") + ("+ld" if cfg.get("double_critic") else ""),
               "sets": len(record.get("hyperparameter_sets", [])), "seeds": int(cfg.get("num_seeds", 0)),
               "disc_return": None, "ci_low": None, "ci_high": None}
        if (rd.path / "summary.json").exists():
            try:
                s = rd.read_summary()
                best = s["sets"][s["best_by_auc"]]["disc_return"]
            except (CheckpointError, KeyError, IndexError, TypeError):
                row["state"] = "damaged"  # summary.json unreadable: listed, not fatal for the other runs
            else:
                row.update(state="finished", disc_return=best["mean"], ci_low=best["ci_low"],
                           ci_high=best["ci_high"])
        elif (rd.path / "checkpoint.json").exists():
            row["state"] = "resumable"
        else:
            row["state"] = "incomplete"
        rows.append(row)
    return rows
