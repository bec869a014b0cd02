"""A run directory's checkpoints (`Checkpoints`, which `RunDir` is): the whole training state written as one unit, its
manifest (checkpoint.json) checked against its own SHA-256, the state's and every chunk's metrics it builds on; see
`_results`'s module docstring for the layout."""

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax

from .._distributed import as_key_like, is_key
from ._files import (CheckpointError, atomic_write_bytes, json_digest, plain, read_or_none, serialise, sha256_of,
                     write_json)


class Checkpoints:
    """The checkpoint methods of a run directory at `self.path`."""

    path: Path

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
        except FileNotFoundError:  # (the run finished, clearing its checkpoint, since a reader saw it: callers retry)
            raise CheckpointError(f"No checkpoint in {where!r} (no checkpoint.json): the run stopped before its first "
                                  f"checkpoint or finished (see summary.json).") from None
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
