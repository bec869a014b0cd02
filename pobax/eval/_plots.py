"""Learning-curve figures: mean over seeds with a shaded 95% bootstrap confidence interval."""

import os
import warnings
import zlib
from pathlib import Path

import numpy as np
import pandas as pd

from ..agent import NUMERIC, config_from_dict
from ._args import as_path, check_bools
from ._files import check_figure_path, has_config, save_figure
from ._listing import runs_below
from ._given_env import trained_env
from ._results import RunDir, write_json
from ._stats import bootstrap_ci, diverged_seeds, summarize

#: Colours of the benchmark's agents (the paper's figure: floor grey, ceiling green) and of the zoo's memories.
AGENT_COLORS = {"floor": "tab:gray", "gru": "tab:blue", "ld": "tab:orange", "trxl": "tab:purple",
                "ceiling": "tab:green", "lstm": "tab:red", "lru": "tab:brown", "s6": "tab:pink", "ffm": "tab:olive"}
_OTHER_COLORS = ("tab:cyan", "black", "gold", "navy", "teal", "magenta")


def agent_color(name: str) -> str:
    """The colour of an agent by its name (a label's first word): the benchmark's and the zoo's own, for any other
    memory (a user's cell) one of a few colours they do not use, the same in every figure."""
    name = name.split(" ")[0]
    return AGENT_COLORS.get(name) or _OTHER_COLORS[zlib.crc32(name.encode()) % len(_OTHER_COLORS)]


def seed_bins(metrics: pd.DataFrame, column: str = "disc_return", points: int = 50, hp_index: int = 0):
    """(env steps, seeds, per-seed values) of one hyperparameter set's `column`: each seed's updates averaged into
    `points` bins of equal numbers of updates (a bin's env step is its last), as a (seeds, bins) array. Diverged runs
    (a non-finite loss, the metric `nonfinite`) are left out, as they are from the statistics (`summarize`)."""
    df = metrics[metrics.hp_index == hp_index]
    steps = np.sort(df.env_step.unique())
    edges = np.linspace(0, len(steps), min(points, len(steps)) + 1).astype(int)
    diverged = set(diverged_seeds(df))
    seeds, per_seed = [], []
    for seed, g in df.groupby("seed"):
        if seed in diverged:
            continue
        v = g.sort_values("env_step")[column].to_numpy(np.float64)
        with warnings.catch_warnings():  # a bin in which no episode ended is NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            per_seed.append([np.nanmean(v[a:b]) if b > a else np.nan for a, b in zip(edges[:-1], edges[1:])])
        seeds.append(int(seed))
    per_seed = np.asarray(per_seed, np.float64).reshape(len(per_seed), len(edges) - 1)
    return np.array([steps[b - 1] for b in edges[1:]]), seeds, per_seed


def curve_with_ci(metrics: pd.DataFrame, column: str = "disc_return", points: int = 50, hp_index: int = 0):
    """(env steps, mean, low, high) of a learning curve, averaged into `points` bins per seed first (`seed_bins`)."""
    x, _, per_seed = seed_bins(metrics, column, points, hp_index)
    return (x, *_ci_by_bin(per_seed))


def _ci_by_bin(per_seed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, low, high) over seeds of each bin of a (seeds, bins) array."""
    stats = np.array([bootstrap_ci(per_seed[:, j], n_resamples=2000) for j in range(per_seed.shape[1])])
    return stats[:, 0], stats[:, 1], stats[:, 2]


def plot_band(ax, x, mean, low, high, *, label: str, color: str | None = None, alpha: float = 0.25,
              lw: float | None = None):
    """A learning curve as its mean line and CI band on `ax`, through the bins that hold a value: a bin in which no
    episode ended (NaN, or None in a record) is skipped, not drawn as a gap, since environments whose episodes all
    end at once (HalfCheetah: 1000 steps, never terminated) finish none in most bins. Returns the line."""
    x, mean, low, high = (np.asarray(v, np.float64) for v in (x, mean, low, high))
    keep = np.isfinite(mean)
    (line,) = ax.plot(x[keep], mean[keep], label=label, color=color, lw=lw)
    band = keep & np.isfinite(low) & np.isfinite(high)
    ax.fill_between(x[band], low[band], high[band], alpha=alpha, color=line.get_color())
    return line


def discounted_references(reference: dict[str, float], prefix: str = "") -> dict[str, float]:
    """An environment's reference values that sit on the discounted-return scale of the curves (Battleship's
    γ = 1: its returns are both), as labelled horizontal lines."""
    return {f"{prefix}{k.replace('_', ' ')}": v for k, v in reference.items()
            if k.endswith("return") and "undiscounted" not in k and isinstance(v, int | float)
            and not isinstance(v, bool)}


def plot_learning_curves(
    curves: dict[str, pd.DataFrame],
    path: str | Path,
    *,
    column: str = "disc_return",
    title: str = "",
    hlines: dict[str, float] | None = None,
    agent_colors: bool = False,
) -> Path:
    """One figure: every labelled run as mean ± 95% CI, plus horizontal reference lines. `agent_colors`: the labels
    start with agent names (floor, gru, ...), coloured as in every gap and benchmark figure."""
    bands = {label: curve_with_ci(metrics, column) for label, metrics in curves.items()}
    return _draw_bands(bands, path, column=column, title=title, hlines=hlines, agent_colors=agent_colors)


def _draw_bands(bands: dict[str, tuple], path: str | Path, *, column: str, title: str = "",
                hlines: dict[str, float] | None = None, agent_colors: bool = False) -> Path:
    """The figure of `plot_learning_curves` from curves already reduced to (env steps, mean, low, high)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, band in bands.items():
        plot_band(ax, *band, label=label, color=agent_color(label) if agent_colors else None)
    for label, y in (hlines or {}).items():
        ax.axhline(y, ls="--", lw=1, color="black", alpha=0.7)
        ax.annotate(label, (0.01, y), xycoords=("axes fraction", "data"), va="bottom", fontsize=8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel({"disc_return": "discounted return", "return": "return"}.get(column, column))
    ax.set_title(title)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    check_figure_path(path)
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def plot_runs(runs, path: str | Path = "curves.png", *, best: bool = False, column: str = "disc_return",
              data: str | Path | None = None) -> Path:
    """Learning curves of run directories (one path, or a list of them; finished or interrupted) in one figure
    written to `path`, labelled by environment, agent and hyperparameters; each run's first hyperparameter set, or
    its best by AUC with `best`. `column`: any numeric column of the runs' metrics (`disc_return`, `return`, or a
    training metric such as `entropy`, `ep_length`, `approx_kl`). `data`: also write the curves as JSON (per label:
    env steps, mean and 95% CI, and each seed's binned values); an existing file there that is not such curves (a
    run's summary.json, notes) is refused, not written over. Paths may start with `~`. Returns the figure's path."""
    check_bools("plot_runs", ValueError, best=best)
    path = as_path("plot_runs", "path", path, what="a file path")
    data = as_path("plot_runs", "data", data, none=True, what="a file path")
    runs = [runs] if isinstance(runs, (str, os.PathLike)) else runs
    runs = [as_path("plot_runs", "runs", run, what="a run directory's path") for run in runs]
    if data is not None and data.resolve() == path.resolve():
        raise ValueError(f"--json {str(data)!r} is the figure's own path (--out): give the curves another file.")
    if data is not None and os.path.lexists(data) and not is_curves_json(data):  # (before anything is read or drawn)
        raise ValueError(f"--json {str(data)!r} exists and is not curves plot wrote: pass another --json, or move "
                         f"the file away (plot writes over only its own curves).")
    curves, hlines, sources = {}, {}, {}
    for run in runs:
        rd = RunDir(run)
        if not has_config(rd.path):
            raise FileNotFoundError(f"{str(rd.path)!r} is not a run directory (no config.json){runs_below(rd.path)}.")
        record = rd.read_config()
        cfg = config_from_dict(record["config"], source=repr(str(rd.path / "config.json")))
        metrics = rd.metrics()  # (a finished run's, its seal checked: an edited config.json is refused)
        if column not in metrics.columns or not pd.api.types.is_numeric_dtype(metrics[column]):
            settings = {"hp_index", "seed", "update", "env_step", *NUMERIC}
            known = ", ".join(c for c in metrics.columns
                              if pd.api.types.is_numeric_dtype(metrics[c]) and c not in settings)
            raise ValueError(f"{str(rd.path)!r} logs no metric {column!r}; its metrics are: {known}.")
        h = 0
        if best:  # the run's own selection (paper criterion), from its metrics (so far, for an unfinished run)
            h = summarize(cfg, metrics)["best_by_auc"]
        hp = cfg.grid()[h]  # (the configuration's, not config.json's list of them, which it derives from)
        agent = cfg.memory + (" + λ-discrepancy" if cfg.double_critic else "")
        if cfg.encoder != "auto":
            agent += f" [{cfg.encoder}]"
        env, observability = trained_env(record)
        label = f"{env} {observability} {agent} (lr={hp['lr']:g}, λ0={hp['lambda0']:g})"
        if label in curves:  # two runs alike in all of the above: tell them apart by directory
            label += f" {rd.path}"
        base, n = label, 2
        while label in curves:  # (one directory given twice)
            label, n = f"{base} ({n})", n + 1
        mine = metrics[metrics.hp_index == h]
        diverged = diverged_seeds(mine)
        if diverged:
            label += f" [{len(diverged)} of {mine.seed.nunique()} seeds diverged, left out]"
        curves[label] = mine.assign(hp_index=0)
        sources[label] = str(rd.path)
        if column == "disc_return" and observability != "given":  # (a given environment's are not cfg.env's)
            reference = (record.get("env_spec") if isinstance(record.get("env_spec"), dict) else {}).get("reference")
            hlines.update(discounted_references(reference if isinstance(reference, dict) else {}, f"{cfg.env}: "))
    binned = {label: seed_bins(m, column) for label, m in curves.items()}  # each curve reduced once, for both
    bands = {label: (x, *_ci_by_bin(per_seed)) for label, (x, _, per_seed) in binned.items()}
    figure = _draw_bands(bands, path, column=column, hlines=hlines)
    if data is not None:
        write_json(Path(data), {"column": column, "curves": {
            label: _curve_data(bands[label], *binned[label][1:]) | {"run_dir": sources[label]} for label in curves}})
    return figure


def is_curves_json(path: Path) -> bool:
    """Whether `path` is a file of curves that `plot_runs` (`plot --json`) wrote: a column and its curves."""
    import json

    if not path.is_file():  # (a FIFO would wait for a writer)
        return False
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return False
    return isinstance(data, dict) and set(data) == {"column", "curves"}


def _curve_data(band: tuple, seeds: list[int], per_seed: np.ndarray) -> dict:
    """A curve as JSON: env steps, mean and 95% CI over seeds, and each seed's binned values (NaN as null)."""
    x, mean, low, high = band
    clean = lambda v: [None if not np.isfinite(a) else round(float(a), 6) for a in v]  # noqa: E731
    return {"env_step": [int(a) for a in x], "mean": clean(mean), "low": clean(low), "high": clean(high),
            "per_seed": {str(s): clean(row) for s, row in zip(seeds, per_seed)}}
