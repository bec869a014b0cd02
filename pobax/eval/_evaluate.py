"""`evaluate`: fresh episodes of a trained agent (`_episodes`), measured per set and per run, written as an
evaluation's .json and .csv."""

import dataclasses
import hashlib
import os
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from .._paths import printable
from ..agent import NUMERIC
from ._episodes import (EvalError, check_count, check_obs_norm, episode_env, episode_keys, episode_limit, jit_for,
                        play_episodes)
from ._args import as_path, check_bools
from ._load import LoadedRun, diverged_runs, load_run
from ._files import CheckpointError, atomic_write_text, check_output_dir, read_json, serialise, write_json
from ._locks import lock_file
from ._stats import diverged_seeds, format_ci, mean_ci


#: The lock (`lock_file`) that evaluations writing into one directory at once take in turn.
EVAL_LOCK = ".eval.lock"


@dataclasses.dataclass
class EvalResult:
    """What `evaluate` returns: one row per episode (`episodes`: hyperparameter set, seed index, episode, return,
    discounted return, length, how it ended, the environment's episode metrics), the `summary` (per set: mean and
    95% CI over seeds of each seed's mean; per run: over its episodes; `mean_ci`'s method) and the files written."""

    episodes: pd.DataFrame
    summary: dict
    files: list[Path]


def _stat(values) -> dict:
    """Mean and 95% interval as every table of pobax gives one (`mean_ci`: a percentile bootstrap from 10 values,
    Student's t below, where a bootstrap of a handful of values has too few distinct resamples)."""
    ci = mean_ci(np.asarray(values, np.float64))
    return {"mean": ci["mean"], "ci_low": ci["ci_low"], "ci_high": ci["ci_high"]}


def evaluate(
    run: LoadedRun | str | os.PathLike,
    *,
    episodes: int = 10,
    greedy: bool = False,
    observability: str | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    out: str | os.PathLike | None = None,
    save: bool = True,
) -> EvalResult:
    """Play `episodes` fresh episodes with every run (hyperparameter set × seed) of a run directory (a path or a
    `load_run` result) and measure them: returns (undiscounted and discounted), episode lengths and the
    environment's episode metrics; per set the mean and 95% CI over seeds (of each seed's mean over its episodes;
    seeds whose training diverged are counted, `diverged`, and left out), per run the mean and 95% CI over its
    episodes: a percentile bootstrap from 10 values, Student's t below (`mean_ci`, as the training summaries).

    The policy samples its actions (`greedy=True`: the most probable action). `observability` plays another
    observability of the same environment (observations must have the shape the network was trained on).
    Deterministic for a `seed`. Episodes still running after `max_steps` steps (default: the environment's time
    limit) are cut and counted in `cut`. With `save`, writes `eval-<observability>-<policy>-seed<seed>.json` (the
    summary) and `.csv` (the episodes) into `out` (default: the run directory; an unfinished run's checkpoint adds
    `-chunk<N>`, so its finished model's evaluation is written beside it later); an existing evaluation of other
    settings or another model there is refused, not written over. A run trained in an environment given to
    `train(env=...)` plays that one (load it with `load_run(path, env=...)`), named by its classes and observability
    "given" in the summary and the files' names. `out` may start with `~`; arguments of the wrong kind are refused
    (EvalError) before anything is played."""
    if not isinstance(greedy, bool | np.bool_):
        raise EvalError(f"greedy must be True or False, got {greedy!r}.")
    greedy = bool(greedy)
    check_bools("evaluate", EvalError, save=save)
    out = as_path("evaluate", "out", out, EvalError, none=True, what="a directory path")  # ("": the cwd)
    if save and out is not None:  # (before anything is played)
        check_output_dir(out, "eval writes its .json and .csv files", EvalError)
    run = load_run(run) if not isinstance(run, LoadedRun) else run
    cfg = run.config
    check_count("--episodes", episodes)
    check_obs_norm(run)
    if diverged_runs(run).all():  # (a model with non-finite parameters where training did not diverge: load_run's)
        raise EvalError(f"Every run of {str(run.path)!r} diverged in training: there is no policy to evaluate (its "
                        f"parameters are not finite); train it again, e.g. with a smaller --lr"
                        + (f" or --reward-scale (it trained at {cfg.reward_scale:g})." if cfg.reward_scale != 1 else "."))
    env = episode_env(run, observability)
    obs_name = "given" if run.trained_env[1] == "given" else observability or cfg.observability
    limit = episode_limit(env, max_steps)
    settings = dict(observability=obs_name, greedy=greedy, episodes=episodes, seed=seed, max_steps=limit)
    target = out if out is not None else run.path
    # a checkpoint's evaluation is named after its chunk: the finished model's, later, is another evaluation
    at = f"-chunk{run.chunks_done}" if run.chunks_done is not None else ""
    stem = f"eval-{obs_name}-{'greedy' if greedy else 'stochastic'}-seed{seed}{at}"
    identity = {**settings, "model": run.source, "model_sha256": hashlib.sha256(serialise((run.model, run.obs_norm)))
                .hexdigest(), "run_dir": str(run.path.resolve()) if run.path else None}
    if save and target is not None:
        _check_not_overwriting(target / f"{stem}.json", identity)
    keys = episode_keys(seed, episodes)
    play = jit_for(lambda m, o, e, k: jax.vmap(lambda mm, oo: play_episodes(mm, oo, e, k, greedy, limit))(m, o), cfg)
    s = jax.device_get(play(run.model, run.obs_norm, env, keys))
    names = [name for k in s["metrics"] for name in env.episode_metrics[k]]
    metric_values = np.concatenate([np.asarray(s["metrics"][k]) for k in s["metrics"]], axis=-1) if names else None
    runs, n = run.num_runs, episodes
    cols = {"hp_index": np.repeat(run.hp_index, n), "seed": np.repeat(run.seed_index, n),
            "episode": np.tile(np.arange(n), runs), "return": s["ret"].reshape(-1),
            "disc_return": s["disc_ret"].reshape(-1), "length": s["length"].reshape(-1).astype(np.int64),
            "terminated": s["terminated"].reshape(-1), "truncated": s["truncated"].reshape(-1),
            "cut": ~s["done"].reshape(-1)}
    for j, name in enumerate(names):
        cols[name] = metric_values[..., j].reshape(-1)
    df = pd.DataFrame(cols)
    summary = _summary(run, df, names, identity)
    files = []
    if save and target is not None:
        target.mkdir(parents=True, exist_ok=True)
        files = [target / f"{stem}.json", target / f"{stem}.csv"]
        handle = lock_file(target / EVAL_LOCK, wait=True)  # evaluations into one --out at once: one writes at a time
        try:
            _check_not_overwriting(files[0], identity)  # again: another eval may have written it while this one played
            write_json(files[0], summary)
            atomic_write_text(files[1], df.to_csv(index=False))
        finally:
            if handle is not None:
                handle.close()
    return EvalResult(df, summary, files)


def _check_not_overwriting(path: Path, settings: dict) -> None:
    """An EvalError, before anything is played, where `path` holds an evaluation of other settings, model (its
    SHA-256, where the evaluation holds one) or run directory (the same ones play the same episodes: that one is
    written again) or a file eval did not write (its .json, or its .csv alone)."""
    if not path.exists():
        if path.with_suffix(".csv").exists():
            raise EvalError(f"{str(path.with_suffix('.csv'))!r} exists and is not an evaluation eval wrote; pass "
                            f"another --out (or --seed), or move the file away.")
        return
    try:
        old = read_json(path)
        differ = [k for k, v in settings.items() if old.get(k) != v and (k in old or k != "model_sha256")]
    except (CheckpointError, OSError, TypeError, KeyError, AttributeError):  # not JSON, or not an evaluation's
        raise EvalError(f"{str(path)!r} exists and is not an evaluation eval wrote; pass another --out (or --seed), "
                        f"or move the file away.") from None
    if differ:
        what = ", ".join(f"{k} {old.get(k)!r} (now {settings[k]!r})" for k in differ)
        raise EvalError(f"{str(path)!r} holds an evaluation of other settings ({what}); eval does not write over "
                        f"it: pass another --out (or --seed), or move the file away.")




def _summary(run: LoadedRun, df: pd.DataFrame, names: list[str], identity: dict) -> dict:
    cfg = run.config
    measured = ["return", "disc_return", "length", *names]
    sets, per_run = [], []
    for h, hp in enumerate(cfg.grid()):
        d = df[df.hp_index == h]
        # as in the training summary: a seed whose training diverged is counted, never averaged in
        diverged = diverged_seeds(run.metrics[run.metrics.hp_index == h])
        per_seed = d.groupby("seed")[measured].mean()
        num_seeds = len(per_seed)
        per_seed = per_seed.drop(index=[sd for sd in diverged if sd in per_seed.index])
        row = {"hp_index": h, **hp, "num_seeds": num_seeds, "diverged": len(diverged), "diverged_seeds": diverged,
               "episodes": len(d), "cut": int(d["cut"].sum()),
               "terminated": int(d["terminated"].sum()), "truncated": int(d["truncated"].sum())}
        for col in ["return", "disc_return", "length"]:
            row[col] = {**_stat(per_seed[col]), "per_seed": per_seed[col].tolist()}
        row["episode_metrics"] = {m: _stat(per_seed[m]) for m in names}
        sets.append(row)
        for seed, g in d.groupby("seed"):
            per_run.append({"hp_index": h, "seed": int(seed),
                            **{col: _stat(g[col]) for col in ["return", "disc_return", "length"]}})
    env, trained = run.trained_env
    return {"run": str(run.path) if run.path else None, "env": env, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "trained_observability": trained, **identity,
            "best_by_auc": run.best_set, "sets": sets, "runs": per_run}


def format_eval(result: EvalResult) -> str:
    """The evaluation as text: per hyperparameter set, mean [95% CI] over seeds of the returns, the length and the
    episode metrics that are not all zero; then one line per run, mean [95% CI] over its episodes (with one seed, the
    set's interval over seeds is NaN: undefined)."""
    s = result.summary
    policy = "greedy" if s["greedy"] else "stochastic"
    agent = s["memory"] + (" + λ-discrepancy" if s["double_critic"] else "")
    lines = [f"{s['env']} {agent} (trained on {s['trained_observability']}) on {s['observability']}: "
             f"{s['episodes']} episodes per run, {policy} policy, seed {s['seed']}, model: {s['model']}"]
    swept = [k for k in NUMERIC if len({r[k] for r in s["sets"]}) > 1] or ["lr", "lambda0"]
    for r in s["sets"]:
        hp = ", ".join(f"{k}={r[k]:g}" for k in swept)
        best = " (best by AUC)" if len(s["sets"]) > 1 and r["hp_index"] == s["best_by_auc"] else ""
        lines.append(f"  set {r['hp_index']} ({hp}){best}, {r['num_seeds']} seeds: "
                     f"discounted {format_ci(r['disc_return'])}"
                     f"  undiscounted {format_ci(r['return'])}  length {r['length']['mean']:.1f}")
        if r.get("diverged"):
            lines.append(f"    {r['diverged']} of {r['num_seeds']} seeds diverged in training (left out of the set's "
                         f"figures; their runs are listed below)")
        shown = {k: v for k, v in r["episode_metrics"].items() if v["mean"] != 0}
        if shown:
            lines.append("    " + "  ".join(f"{k} {v['mean']:.3f}" for k, v in shown.items()))
        if r["cut"]:
            lines.append(f"    {r['cut']} of {r['episodes']} episodes cut at {s['max_steps']} steps (counted as they "
                         f"stood)")
    lines.append("  per run, over its episodes:")
    for r in s["runs"]:
        lines.append(f"    set {r['hp_index']} seed {r['seed']}: discounted {format_ci(r['disc_return'])}  "
                     f"undiscounted {format_ci(r['return'])}  length {r['length']['mean']:.1f}")
    if result.files:
        lines.append("written: " + ", ".join(printable(f) for f in result.files))
    return "\n".join(lines)
