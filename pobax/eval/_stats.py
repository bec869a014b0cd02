"""Statistics over seeds: bootstrap confidence intervals, interquartile mean, area under the curve."""

import numpy as np


def bootstrap_ci(
    x, confidence: float = 0.95, n_resamples: int = 10_000, seed: int = 0
) -> tuple[float, float, float]:
    """Mean of `x` (one value per seed) with a percentile-bootstrap confidence interval of the mean.

    NaNs are dropped. One value gives a zero-width interval; no values give NaNs.
    """
    x = np.asarray(x, np.float64)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(x.mean())
    if x.size == 1:
        return mean, mean, mean
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(n_resamples, x.size))
    means = x[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return mean, float(lo), float(hi)


def iqm(x) -> float:
    """Interquartile mean: the mean of the middle 50% (drops `floor(n/4)` values at each end, like
    `scipy.stats.trim_mean(x, 0.25)`)."""
    x = np.sort(np.asarray(x, np.float64)[~np.isnan(np.asarray(x, np.float64))])
    if x.size == 0:
        return float("nan")
    k = int(0.25 * x.size)
    return float(x[k : x.size - k].mean())


def auc(values) -> float:
    """Area under a learning curve sampled once per update, normalised by its length.

    With updates of equal size this is the trapezoid-free average of the curve over training: the area under
    the curve of (env steps, return) divided by the total number of env steps. Missing points (updates in which
    no episode finished) are dropped. This is the paper's hyperparameter selection criterion.
    """
    v = np.asarray(values, np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def final_value(values, fraction: float = 0.1) -> float:
    """The mean of the last `fraction` (at least one point) of a learning curve's defined points.

    Updates in which no episode finished have no return (NaN); they are dropped first, so the final value is
    taken over the last points at which the agent's returns were observed.
    """
    v = np.asarray(values, np.float64)
    v = v[~np.isnan(v)]
    if v.size == 0:
        return float("nan")
    n = max(1, int(round(v.size * fraction)))
    return float(v[-n:].mean())


def diverged_seeds(metrics) -> list[int]:
    """The seeds of `metrics` (one hyperparameter set's rows) whose training diverged: an update's loss or gradient
    was not finite (the metric `nonfinite`). Every statistic, curve and selection leaves them out, counted."""
    if "nonfinite" not in metrics:
        return []
    return sorted(int(s) for s in metrics.seed[metrics.nonfinite > 0].unique())


def _over_seeds(values: list[float]) -> dict:
    """One value per seed: mean, 95% bootstrap CI and the values."""
    mean, lo, hi = bootstrap_ci(values)
    return {"mean": mean, "ci_low": lo, "ci_high": hi, "per_seed": values}


def summarize(cfg, metrics, episode_metrics: tuple[str, ...] = ()) -> dict:
    """Per hyperparameter set of `cfg` (a `TrainConfig`), discounted and undiscounted: final returns (`final_value`
    per seed) and the area under the learning curve (`auc`), each as mean and 95% bootstrap CI over the seeds that
    did not diverge. A run diverged when an update's loss or gradient was not finite (the metric `nonfinite`): it is
    counted (`diverged`, `diverged_seeds`), never averaged in. `best_by_auc` is the set with the largest mean AUC of
    the discounted return (the paper's selection criterion) among the sets with no diverged run (among all sets if
    every set has one: then `all_sets_diverged`). `episode_metrics` names columns of per-episode quantities (the
    environment's `episode_metrics`, e.g. Craftax's achievement success rates): their final values, the same way,
    under each set's `episode_metrics`."""
    sets = []
    for h, hp in enumerate(cfg.grid()):
        df = metrics[metrics.hp_index == h]
        row = {"hp_index": h, **hp}
        seeds = [(s, g.sort_values("update")) for s, g in df.groupby("seed")]
        diverged = diverged_seeds(df)
        healthy = [g for s, g in seeds if int(s) not in diverged]
        row["diverged"], row["diverged_seeds"], row["num_seeds"] = len(diverged), diverged, len(seeds)
        finals = lambda col: _over_seeds([final_value(g[col].to_numpy()) for g in healthy])  # noqa: E731
        for col in ("return", "disc_return"):
            row[col] = finals(col)
            row[f"{col}_auc"] = _over_seeds([auc(g[col].to_numpy()) for g in healthy])
        row["episode_metrics"] = {col: finals(col) for col in episode_metrics if col in df}
        sets.append(row)
    clean = [i for i, s in enumerate(sets) if s["diverged"] == 0]
    pool = clean or list(range(len(sets)))
    score = lambda i: -np.inf if np.isnan(sets[i]["disc_return_auc"]["mean"]) else sets[i]["disc_return_auc"]["mean"]  # noqa: E731
    return {"env": cfg.env, "observability": cfg.observability, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "num_seeds": cfg.num_seeds, "final_fraction": 0.1,
            "best_by_auc": max(pool, key=score), "all_sets_diverged": not clean,
            "diverged_runs": sum(s["diverged"] for s in sets), "sets": sets}
