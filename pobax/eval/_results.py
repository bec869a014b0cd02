"""Run directories: resolved config, tidy metrics table, model parameters, summary.

Layout of a run directory:

    config.json         the resolved configuration (and the hyperparameter sets, by index)
    metrics/NNNNN.csv   one file per chunk of updates, written as they come
    metrics.csv         all chunks, written at the end
    model.eqx           final parameters of every run (hyperparameter set × seed), `eqx.tree_serialise_leaves`
    summary.json        final returns per hyperparameter set: mean and 95% CI over seeds

Every file is written to a temporary name in the same directory and then renamed, so an interrupted run never
leaves a half-written file, and nothing already written is overwritten by a new run.
"""

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import equinox as eqx
import pandas as pd


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
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


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n")


class RunDirExistsError(FileExistsError):
    pass


class RunDir:
    """A run directory (see the module docstring)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    @classmethod
    def create(cls, path: str | os.PathLike) -> "RunDir":
        """Create a new run directory; refuses to reuse one that already holds results."""
        p = Path(path)
        if p.exists() and any(p.iterdir()):
            raise RunDirExistsError(
                f"Run directory {str(p)!r} already exists and is not empty; pass another --out, or remove it "
                f"if you no longer need its results."
            )
        (p / "metrics").mkdir(parents=True, exist_ok=True)
        return cls(p)

    def write_config(self, config: dict) -> None:
        write_json(self.path / "config.json", config)

    def read_config(self) -> dict:
        return json.loads((self.path / "config.json").read_text())

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

    def write_metrics(self, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics.csv", df.to_csv(index=False))

    def save_model(self, model: eqx.Module) -> None:
        path = self.path / "model.eqx"
        fd, tmp = tempfile.mkstemp(dir=self.path, prefix=".model.", suffix=".tmp")
        os.close(fd)
        try:
            eqx.tree_serialise_leaves(tmp, model)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    def load_model(self, like: eqx.Module) -> eqx.Module:
        path = self.path / "model.eqx"
        if not path.exists():
            raise FileNotFoundError(f"No model in {str(self.path)!r} (expected {str(path)!r}).")
        return eqx.tree_deserialise_leaves(path, like)

    def write_summary(self, summary: dict) -> None:
        write_json(self.path / "summary.json", summary)

    def read_summary(self) -> dict:
        return json.loads((self.path / "summary.json").read_text())


def list_runs(root: str | os.PathLike) -> list[dict]:
    """Every run directory under `root` (a directory with config.json and metrics): its environment, agent,
    number of hyperparameter sets and seeds, state (finished / resumable / incomplete) and, when finished, the
    final discounted return of its best set by AUC (mean and 95% CI over seeds)."""
    rows = []
    for cfg_path in sorted(Path(root).rglob("config.json")):
        rd = RunDir(cfg_path.parent)
        try:
            record = rd.read_config()
            cfg = record["config"]
        except (json.JSONDecodeError, KeyError):
            continue
        row = {"path": str(rd.path), "env": cfg.get("env", "?"), "observability": cfg.get("observability", "?"),
               "agent": cfg.get("memory", "?") + ("+ld" if cfg.get("double_critic") else ""),
               "sets": len(record.get("hyperparameter_sets", [])), "seeds": int(cfg.get("num_seeds", 0)),
               "disc_return": None, "ci_low": None, "ci_high": None}
        if (rd.path / "summary.json").exists():
            s = rd.read_summary()
            best = s["sets"][s["best_by_auc"]]["disc_return"]
            row.update(state="finished", disc_return=best["mean"], ci_low=best["ci_low"], ci_high=best["ci_high"])
        elif (rd.path / "checkpoint.json").exists():
            row["state"] = "resumable"
        else:
            row["state"] = "incomplete"
        rows.append(row)
    return rows
