"""A run directory's metrics (`RunMetrics`, which `RunDir` is): each chunk's table as it is trained, the whole run's
`metrics.csv` at its end, and reading them back, an unfinished run's through its checkpoint, a finished run's through
its seal; see `_results`'s module docstring for the layout."""

import os
from pathlib import Path

import pandas as pd

from ..agent import config_from_dict
from ._files import CheckpointError, atomic_write_text
from ._metrics_table import ordered_metrics, read_metrics


class RunMetrics:
    """The metrics methods of a run directory at `self.path` (with `Checkpoints`' and `RunDir`'s: `check_unfinished`,
    `verified_chunks`, `read_config`, `read_summary`)."""

    def write_chunk(self, index: int, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics" / f"{index:05d}.csv", df.to_csv(index=False))

    def metrics(self) -> pd.DataFrame:
        """The metrics table: `metrics.csv` if the run finished; else the chunks its checkpoint has trained, checked
        as a resume checks them (`check_unfinished`), or before its first checkpoint every chunk written so far."""
        full, finished = self.path / "metrics.csv", os.path.lexists(self.path / "summary.json")
        if not finished:
            try:
                return self._unfinished_metrics()
            except (CheckpointError, OSError):
                if not os.path.lexists(self.path / "summary.json"):
                    raise
            # it finished while it was read (its checkpoint cleared): read as finished, through its seal
        # (a link there to itself or to nothing: read_summary names it)
        self.read_summary()  # finished: its seal checked (the configuration below, the metrics table)
        # (an unfinished run's metrics.csv, written before a kill, is not what its checkpoint trained)
        if not os.path.lexists(full):
            raise CheckpointError(f"{str(full)!r} is missing: the run finished (summary.json) with its metrics "
                                  f"table there; restore it (its chunks' files are not what it finished with).")
        return self.check_rows(read_metrics(full), full)

    def _unfinished_metrics(self) -> pd.DataFrame:
        """`metrics` of a run without summary.json; a CheckpointError where it finished while it was read (its chunks
        are then not what its seal covers: `metrics` reads it again, finished)."""
        self.check_unfinished()
        if (self.path / "checkpoint.json").exists():
            return self.chunk_metrics(self.verified_chunks())
        if os.path.lexists(self.path / "summary.json"):
            raise CheckpointError(f"The run in {str(self.path)!r} finished while it was read.")
        chunks = sorted((self.path / "metrics").glob("[0-9]*.csv"))
        if not chunks:
            raise FileNotFoundError(f"{str(self.path)!r} holds no metrics yet: its first chunk is not trained (a run "
                                    f"being trained writes them a chunk at a time; `pobax results` shows its state).")
        return pd.concat([read_metrics(c) for c in chunks], ignore_index=True)

    def check_rows(self, df: pd.DataFrame, source: Path) -> pd.DataFrame:
        """`df`, the metrics of the whole run read from `source` (metrics.csv, or every chunk of metrics/), if it holds
        one row per update of each of the run's runs; else a CheckpointError naming `source`."""
        cfg = config_from_dict(self.read_config()["config"], source=repr(str(self.path / "config.json")))
        runs = len(cfg.grid()) * cfg.num_seeds
        if len(df) != runs * cfg.num_updates or df[["hp_index", "seed", "update"]].isna().any(axis=None):
            raise CheckpointError(f"{str(source)!r} holds {len(df):,} rows, not one per update of each of the run's "
                                  f"{runs} runs ({cfg.num_updates:,} updates each): it is damaged (cut short, edited "
                                  f"or a chunk missing); restore it.")
        return df

    def chunk_metrics(self, count: int) -> pd.DataFrame:
        """The metrics of the first `count` chunks as one table, in `metrics.csv`'s order (set, seed, update)."""
        return ordered_metrics(self.chunks(count))

    def write_metrics(self, df: pd.DataFrame) -> None:
        atomic_write_text(self.path / "metrics.csv", df.to_csv(index=False))

    def chunks(self, count: int) -> list[pd.DataFrame]:
        """The metrics of chunks 0 … count - 1."""
        paths = [self.path / "metrics" / f"{c:05d}.csv" for c in range(count)]
        missing = [p.name for p in paths if not p.exists()]
        if missing:
            raise CheckpointError(f"The checkpoint in {str(self.path)!r} is past the metrics written (missing "
                                  f"metrics/{missing[0]}): the run directory is damaged; start a new run.")
        return [read_metrics(p) for p in paths]
