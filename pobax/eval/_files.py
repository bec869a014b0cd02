"""Files written whole: to a temporary name beside the target, then renamed over it (an interrupted write leaves the
old file or none, never half a file), with the permissions the umask gives; and a command's output directory
claimed before anything is written into it (`claim_out`)."""

import errno
import hashlib
import io
import json
import math
import os
import stat
import tempfile
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed (missing, corrupted, or from another configuration)."""


def plain(path: str | os.PathLike, directory: bool = False) -> Path:
    """`path`, unless it exists as what no pobax file is: a directory (unless `directory`: the caller tells one
    apart), a FIFO, a device or a socket (reading one would wait for a writer or never end), a link to nothing (the
    system's "No such file" would name the link as missing) or a link that leads back to itself; then a
    CheckpointError naming it. A missing file is left to the reader."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        if os.path.islink(path):  # (a link to itself is an ELOOP, below)
            raise CheckpointError(f"{str(path)!r} is a symbolic link to {os.readlink(path)!r}, which does not exist: "
                                  f"put the file there, or remove the link.") from None
        return Path(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise CheckpointError(f"{str(path)!r} is a symbolic link that leads back to itself, not the file pobax "
                                  f"wrote there: remove the link and restore the file.") from None
        return Path(path)
    except ValueError:
        return Path(path)
    if stat.S_ISDIR(mode) and not directory:
        raise CheckpointError(f"{str(path)!r} is a directory, not the file pobax wrote there: move it aside and "
                              f"restore the file.")
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise CheckpointError(f"{str(path)!r} is not a regular file (a FIFO, device or socket), so not a file pobax "
                              f"wrote: restore the file, or pass another path.")
    return Path(path)


def has_config(run: str | os.PathLike) -> bool:
    """Whether directory `run` holds a config.json file (a run directory's mark); a CheckpointError naming it where
    it is a link to nothing or a FIFO (`plain`), or a directory beside a run's other files (`RUN_FILES`)."""
    path = plain(Path(run) / "config.json", directory=True)
    if path.is_dir() and any(os.path.lexists(Path(run) / name) for name in RUN_FILES):
        raise CheckpointError(f"{str(path)!r} is a directory, not the configuration file pobax wrote: restore the "
                              f"file.")
    return path.is_file()


#: The files beside config.json that make a directory a run directory, damaged where config.json is not a file.
RUN_FILES = ("summary.json", "checkpoint.json", "sessions.json", "metrics.csv", "model.eqx")


#: The first bytes of each image format a figure or an animation may be written in (matplotlib's and PIL's).
IMAGE_MAGIC = {".png": (b"\x89PNG",), ".gif": (b"GIF8",), ".pdf": (b"%PDF",), ".jpg": (b"\xff\xd8",),
               ".jpeg": (b"\xff\xd8",), ".svg": (b"<?xml", b"<svg"), ".svgz": (b"\x1f\x8b",), ".eps": (b"%!PS",),
               ".ps": (b"%!PS",), ".tif": (b"II*\0", b"MM\0*"), ".tiff": (b"II*\0", b"MM\0*"), ".webp": (b"RIFF",)}


def check_figure_path(path: str | os.PathLike, flag: str = "--out") -> None:
    """Refuse to write a figure or an animation over a file that is not an image of its name's format (a file the
    user keeps under an image's name is not one pobax wrote): FileExistsError naming it. An image of that format
    (an earlier plot or render) is written over; a name of another format is left to the writer."""
    magic = IMAGE_MAGIC.get(Path(path).suffix.lower())
    if magic is None or not os.path.lexists(path):
        return
    try:
        with open(plain(path), "rb") as f:
            head = f.read(8)
    except CheckpointError as e:  # what stands there, without the reader's fix ("restore the file")
        raise FileExistsError(f"{flag} {str(e).rsplit(': ', 1)[0]}: name another file, or move it aside.") from None
    except OSError as e:
        raise FileExistsError(f"{flag} {str(path)!r} exists and cannot be read ({e}): name another file, or move it "
                              f"aside.") from None
    if not head.startswith(magic):
        raise FileExistsError(f"{flag} {str(path)!r} exists and is not a {Path(path).suffix.lower()[1:].upper()} "
                              f"image, so not a figure pobax wrote: name another file, or move it aside.")


def atomic_write_bytes(path: Path, data: bytes, exclusive: bool = False) -> None:
    """`data` written whole to a temporary file, then put in `path`'s place. `exclusive`: only where nothing stands
    at `path`, FileExistsError (nothing written) where something does, also where another process creates it at the
    same moment (the temporary is linked to the name, which fails where the name is taken; a file system without
    links creates the name exclusively, then writes it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _new_temporary(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if not exclusive:
            os.replace(tmp, path)
            return
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise
        except OSError:  # no hard links here
            with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb") as f:
                f.write(data)
        os.unlink(tmp)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, FileExistsError) and e.errno is not None:
            raise OSError(e.errno, e.strerror, str(path)) from e  # named by the file it was writing, not its temporary
        raise


def save_figure(fig, path: Path, dpi: int) -> None:
    """A matplotlib figure written whole (`atomic_write_bytes`, in the format its name's suffix says): a link in its
    place is replaced, never written through to the file it names."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix[1:].lower() or None, dpi=dpi)
    atomic_write_bytes(Path(path), buf.getvalue())


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
    """`obj` as strict JSON: NumPy numbers as numbers (they read back as such), NaN and infinities as null (JSON has
    none; `RunDir.read_summary` gives a summary's back as NaN), anything else unknown as its str."""
    atomic_write_text(path, json.dumps(strict_json(obj), indent=2, sort_keys=False, allow_nan=False,
                                       default=_json_default) + "\n")


def create_json(path: Path, obj: Any) -> None:
    """`write_json`, only where nothing stands at `path` (`atomic_write_bytes`'s `exclusive`): FileExistsError,
    nothing written, where something does."""
    atomic_write_bytes(path, (json.dumps(strict_json(obj), indent=2, allow_nan=False, default=_json_default)
                              + "\n").encode(), exclusive=True)


def strict_json(x: Any) -> Any:
    """`x` with NumPy numbers and arrays as Python's, tuples as lists, and NaN and infinities as None."""
    if isinstance(x, (np.generic, np.ndarray)):
        x = x.tolist() if isinstance(x, np.ndarray) else x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    return x


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def read_json(path: str | os.PathLike) -> Any:
    """A JSON file that pobax wrote; a one-line CheckpointError that names it where it is not valid JSON."""
    path = plain(path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{str(path)!r} is not valid JSON ({e}); the file is damaged: restore it, or pass "
                              f"another directory.") from None


def existing_dir(path: str | os.PathLike, what: str) -> Path:
    """`path` as a Path; a FileNotFoundError naming it unless it is a directory (a mistyped root must not read as one
    with nothing in it)."""
    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"{str(p)!r} is not a directory{'' if p.exists() else ' (it does not exist)'}: pass "
                                f"{what}.")
    return p


def writable_dir(path: Path) -> None:
    """Raise OSError unless a file can be created in the directory `path` (checked by creating one)."""
    fd, tmp = tempfile.mkstemp(dir=path, prefix=".write-check.", suffix=".tmp")
    os.close(fd)
    os.unlink(tmp)


def serialise(tree) -> bytes:
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, jax.device_get(tree))
    return buf.getvalue()


class OutputDirError(ValueError):
    """An output directory that holds something this command did not write."""


def check_output_dir(out: Path, what: str, error: type[Exception] = OutputDirError,
                     named: Path | None = None) -> None:
    """An `error`, before any work, unless `out` can be made a directory and written into: it, or a folder above it,
    is a file or a broken link (left as it is), or the nearest folder that exists cannot be written (read-only, not
    ours). `what` names what the command writes there; `named`, the --out given (default `out`)."""
    given = str(named or out)
    for p in (out, *out.parents):
        if os.path.lexists(p) and not p.is_dir():
            where = f"--out {given!r} is a file" if str(p) == given else f"--out {given!r}: {str(p)!r} is a file"
            raise error(f"{where}{' or a broken link' if not p.exists() else ''}; {what} into a directory: pass "
                        f"another --out, or remove the file.")
    existing = next(p for p in (out, *out.parents) if p.exists())
    writable = os.access(existing, os.W_OK | os.X_OK)
    if writable:  # a file created and removed: os.access says yes to root where none can be (/proc, a read-only mount)
        try:
            writable_dir(existing)
        except OSError:
            writable = False
    if not writable:
        raise error(f"--out {given!r} cannot be written ({str(existing)!r} is not writable); pass another --out.")


#: The file that marks an --out as a command's output directory (sweep and gap write theirs with `claim_out`,
#: benchmark its benchmark.json): the same command run again with that --out continues it.
OUT_MARKERS = {"sweep": "pobax-sweep.json", "gap": "pobax-gap.json", "benchmark": "benchmark.json"}


def claim_out(out: Path, marker: str, owner: dict, reuse: bool = True) -> dict:
    """Make `out` this command's output directory: new or empty, or (with `reuse`) one whose `marker` file says that
    an earlier call of the same command (`owner`, e.g. {"command": "gap", "env": ...}) wrote it. Writes the marker
    where none stands, and returns the marker as `out` holds it (an earlier call's: its values in their order).
    Raises OutputDirError otherwise, before anything is written."""
    def same(held) -> bool:
        return isinstance(held, dict) and {k: held.get(k) for k in owner} == owner

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputDirError(f"--out {str(out)!r} is a file; pass a directory.")
    mark = out / marker
    mine = False
    if out.is_dir() and any(out.iterdir()):
        held = read_json(mark) if os.path.lexists(mark) else None  # (a link to nothing or to itself: named)
        if mark.exists() and not isinstance(held, dict):
            raise OutputDirError(f"--out {str(out)!r} holds a damaged {marker} (a JSON {type(held).__name__}, not an "
                                 f"object): restore it, or pass another --out.")
        mine = same(held)
        if not (reuse and mine):
            if not os.path.lexists(mark):
                raise OutputDirError(f"--out {str(out)!r} holds files and no {marker}, the file by which this command "
                                     f"knows an output directory it wrote: restore {marker} if it wrote this one, or "
                                     f"pass a new or empty directory.")
            raise OutputDirError(f"--out {str(out)!r} holds another call's results; pass a new or empty directory"
                                 + (" (or the --out of an earlier call with the same settings to continue it)."
                                    if reuse else "."))
    try:
        out.mkdir(parents=True, exist_ok=True)
        writable_dir(out)
    except OSError as e:
        raise OutputDirError(f"Cannot write --out {str(out)!r} ({e.strerror or e}); pass another directory.") from None
    if mine:
        return held
    try:  # created only where none stands, even where another call claimed `out` since it was looked at
        create_json(mark, owner)
        return owner
    except FileExistsError:  # another call claimed `out` since it was looked at above: its, unless the same
        held = read_json(mark)
        if not (reuse and same(held)):
            raise OutputDirError(f"--out {str(out)!r} holds another call's results (claimed by another process just "
                                 f"now); pass a new or empty directory.") from None
        return held


def read_or_none(path: Path) -> bytes | None:
    """The bytes of `path`, or None where it cannot be read (missing, or replaced while read)."""
    try:
        return plain(path).read_bytes()
    except (OSError, CheckpointError):
        return None


def sha256_of(path: Path) -> str:
    return hashlib.sha256(plain(path).read_bytes()).hexdigest()


def config_fields_differing(saved: dict, new: dict) -> list[str]:
    """The fields in which two configurations as config.json holds them ("config") differ."""
    norm = lambda d: json.loads(json.dumps(d, default=str))  # noqa: E731  (tuples as lists, as read back)
    a, b = norm(saved), norm(new)
    return [k for k in dict.fromkeys([*b, *a]) if a.get(k) != b.get(k)]


def json_digest(obj: Any) -> str:
    """SHA-256 of `obj` as reading back its JSON (`write_json`) gives it, keys sorted: the same before writing and
    after reading."""
    as_read = json.loads(json.dumps(strict_json(obj), allow_nan=False, default=_json_default))
    return hashlib.sha256(json.dumps(as_read, sort_keys=True).encode()).hexdigest()


#: A summary's statistics, null (`write_json`) where training gave NaN: a set's means, interval bounds and per-seed
#: values, and the run's throughput and compile time.
_NAN_FIELDS = frozenset({"mean", "ci_low", "ci_high", "per_seed", "steps_per_s", "compile_s"})


def nan_for_null(x: Any, field: str | None = None) -> Any:
    """A summary as read back with its statistics' nulls as NaN again, as training returned them (a set whose every
    seed diverged, a run in which no episode ended in the final updates)."""
    if isinstance(x, dict):
        return {k: nan_for_null(v, k) for k, v in x.items()}
    if isinstance(x, list):
        return [nan_for_null(v, field) for v in x]
    return float("nan") if x is None and field in _NAN_FIELDS else x
