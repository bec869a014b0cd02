"""Statistics over seeds: confidence intervals, interquartile mean, area under the curve.

Intervals over seeds (`mean_ci`): a percentile bootstrap of the mean with at least `MIN_SEEDS_FOR_BOOTSTRAP`
values (below that a bootstrap has too few distinct resamples: it understates the spread), else Student's t. A gap
verdict needs at least `MIN_SEEDS_FOR_VERDICT` seeds per agent (`pobax.eval.gap_verdict`).
"""

import numpy as np

#: Seeds from which an interval over seeds is a percentile bootstrap; fewer get a Student-t interval.
MIN_SEEDS_FOR_BOOTSTRAP = 10
#: Seeds below which an agent's interval is too wide to judge a gap with.
MIN_SEEDS_FOR_VERDICT = 5
#: Two-sided 95% quantiles of Student's t with 1-8 degrees of freedom (t_{0.975, df}).
_T975 = (12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060)


def _finite_values(x) -> tuple[np.ndarray, tuple[float, float, float] | None]:
    """`x` without NaNs, and the interval where it needs no computing: NaNs for no value; for one, its value with
    NaN bounds (a spread over one seed is undefined: a zero-width interval would claim certainty); with an infinite
    value, the infinity and NaN bounds."""
    x = np.asarray(x, np.float64)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return x, (float("nan"),) * 3
    if x.size == 1:
        return x, (float(x[0]), float("nan"), float("nan"))
    if np.isinf(x).any():  # a return past float32's range: the mean is the infinity (NaN for both signs), no spread
        up, down = bool(np.isposinf(x).any()), bool(np.isneginf(x).any())
        return x, (float("nan") if up and down else float("inf") if up else float("-inf"), float("nan"), float("nan"))
    return x, None


def format_ci(block: dict, spec: str = ".3f", width: int = 0) -> str:
    """`mean [low, high]` of a statistics block; a missing value (NaN, or null as its JSON holds it) reads "nan";
    a fixed-point `spec` writes magnitudes from 1e7 on with 4 significant digits (2e+37, not 38 digits)."""
    num = lambda v: _number(float("nan") if v is None else float(v), spec)  # noqa: E731
    pad = lambda v, w: num(v).rjust(w)  # noqa: E731
    return f"{pad(block['mean'], width)} [{pad(block['ci_low'], width - 1)}, {pad(block['ci_high'], width - 1)}]"


def _number(v: float, spec: str) -> str:
    return format(v, ".4g" if spec.endswith("f") and abs(v) >= 1e7 and v == v else spec)


def bootstrap_ci(
    x, confidence: float = 0.95, n_resamples: int = 10_000, seed: int = 0
) -> tuple[float, float, float]:
    """Mean of `x` (one value per seed) with a percentile-bootstrap confidence interval of the mean.

    NaNs are dropped. One value gives its value with NaN bounds (no interval); no values give NaNs.
    """
    x, trivial = _finite_values(x)
    if trivial is not None:
        return trivial
    mean = float(x.mean())
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(n_resamples, x.size))
    means = x[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return mean, float(lo), float(hi)


def student_t_ci(x) -> tuple[float, float, float]:
    """Mean of `x` with its two-sided 95% Student-t interval (2 to 9 values; NaNs dropped; one value: NaN bounds)."""
    x, trivial = _finite_values(x)
    if trivial is not None:
        return trivial
    mean = float(x.mean())
    if x.size - 1 > len(_T975):
        raise ValueError(f"student_t_ci takes at most {len(_T975) + 1} values; use bootstrap_ci for more.")
    half = _T975[x.size - 2] * float(x.std(ddof=1)) / np.sqrt(x.size)
    return mean, mean - half, mean + half


def mean_ci(x) -> dict:
    """Mean of `x` (one value per seed, NaNs dropped) with a 95% interval: percentile bootstrap with at least
    `MIN_SEEDS_FOR_BOOTSTRAP` values, Student's t below. Returns {mean, ci_low, ci_high, ci_method, n}."""
    v = np.asarray(x, np.float64)
    n = int((~np.isnan(v)).sum())
    if n >= MIN_SEEDS_FOR_BOOTSTRAP:
        (mean, lo, hi), method = bootstrap_ci(v), "bootstrap"
    else:
        (mean, lo, hi), method = student_t_ci(v), "student-t"
    return {"mean": mean, "ci_low": lo, "ci_high": hi, "ci_method": method, "n": n}


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
    """One value per seed: mean, 95% CI (`mean_ci`) and the values."""
    return {**mean_ci(values), "per_seed": values}


def summarize(cfg, metrics, episode_metrics: tuple[str, ...] = ()) -> dict:
    """Per hyperparameter set of `cfg` (a `TrainConfig`), discounted and undiscounted: final returns (`final_value`
    per seed) and the area under the learning curve (`auc`), each as mean and 95% CI (`mean_ci`) over the seeds that
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
    best, all_diverged = best_by_auc(sets)
    return {"env": cfg.env, "observability": cfg.observability, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "num_seeds": cfg.num_seeds, "final_fraction": 0.1,
            "best_by_auc": best, "all_sets_diverged": all_diverged,
            "diverged_runs": sum(s["diverged"] for s in sets), "sets": sets}


def best_by_auc(sets: list[dict]) -> tuple[int, bool]:
    """The index of the set with the largest mean AUC of the discounted return among `sets` (`summarize`'s rows)
    with no diverged run, or among all of them when every set has one; and whether every set has one."""
    clean = [i for i, s in enumerate(sets) if s["diverged"] == 0]
    pool = clean or list(range(len(sets)))
    score = lambda i: -np.inf if np.isnan(sets[i]["disc_return_auc"]["mean"]) else sets[i]["disc_return_auc"]["mean"]  # noqa: E731
    return max(pool, key=score), not clean
