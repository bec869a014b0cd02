"""Metrics tables: reading what pobax wrote (`metrics.csv`, a chunk's file) and ordering chunks into one table."""

import io
from pathlib import Path

import pandas as pd

from ._files import CheckpointError, plain


#: The columns every metrics table has, all numeric: what curves, statistics and a resume read.
METRIC_COLUMNS = ("hp_index", "seed", "update", "env_step", "return", "disc_return")


def read_metrics(path: Path) -> pd.DataFrame:
    """A metrics table pobax wrote (metrics.csv or a chunk's); a one-line CheckpointError naming the file where it is
    empty, unreadable or lacks its columns."""
    try:
        text = plain(path).read_text()
        if text and not text.endswith("\n"):  # pandas reads a last line cut short as a row of missing values
            raise ValueError("its last line is cut short")
        df = pd.read_csv(io.StringIO(text))
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise CheckpointError(f"{str(path)!r} is not a metrics table pobax wrote ({why}): the file is damaged; "
                              f"restore it.") from None
    bad = [c for c in METRIC_COLUMNS if c not in df or not pd.api.types.is_numeric_dtype(df[c])]
    if bad:
        raise CheckpointError(f"{str(path)!r} is not a metrics table pobax wrote (column {bad[0]!r} "
                              f"{'is not numeric' if bad[0] in df else 'is missing'}): the file is damaged; "
                              f"restore it.")
    return df


def ordered_metrics(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Chunks' metrics as one table ordered by hyperparameter set, seed and update (`metrics.csv`'s order)."""
    return pd.concat(frames, ignore_index=True).sort_values(["hp_index", "seed", "update"], ignore_index=True)
