"""`evaluate`: fresh episodes of a trained agent, and `record_episode`: one episode step by step (for `render`).

The policy acts as in training: `pobax.agent.policy_step` on one observation at a time, the memory reset before
the first observation of each episode (its `starts` flag), the observation normalised by the run's statistics
(frozen). Episode i of seed s starts from the key `fold_in(key(s), i)`, the same for every run of the directory
(common random numbers: every run plays the same worlds), so results are deterministic for a seed.
"""

import dataclasses
import hashlib
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from .._backend import compiler_options
from ..agent import NUMERIC, EpisodeStats, make_env, policy_step
from ..agent._config import INT32_MAX
from ..env import AutoReset, DictSpace, TimeLimitState, spec
from ..env._base import check_seed
from ..env._wrappers import tree_select
from ..memory import TrXLCarry
from ._load import LoadedRun, diverged_runs, load_run, missing_obs_norm
from ._files import (CheckpointError, atomic_write_text, check_output_dir, lock_file, read_json, serialise,
                     write_json)
from ._stats import bootstrap_ci, diverged_seeds, format_ci


#: The lock (`lock_file`) that evaluations writing into one directory at once take in turn.
EVAL_LOCK = ".eval.lock"


class EvalError(ValueError):
    """Evaluation settings that cannot be honoured (e.g. an observability the network cannot read)."""


def _obs_shape(space) -> tuple:
    return tuple((space["obs"] if isinstance(space, DictSpace) else space).shape)


def episode_env(run: LoadedRun, observability: str | None = None):
    """The environment to play fresh episodes in: the run's (or another `observability` of the same environment,
    which must give observations of the shape the network was trained on), with its time limit and without
    auto-reset."""
    cfg = run.config
    obs = cfg.observability if observability is None else observability
    given, trained = run.trained_env
    if trained == "given" and obs != cfg.observability:  # make_env would build cfg.env's, not the one it trained in
        raise EvalError(f"{str(run.path)!r} trained in an environment given to train(env=...) ({given}): another "
                        f"observability ({obs!r}) would play {cfg.env}'s registered one; play it without one.")
    env = run.env if obs == cfg.observability else make_env(cfg, obs)
    want, got = _obs_shape(run.env.observation_space), _obs_shape(env.observation_space)
    if got != want or isinstance(env.observation_space, DictSpace) != isinstance(run.env.observation_space, DictSpace):
        same = [o for o in spec(cfg.env).observabilities
                if _obs_shape(make_env(cfg, o).observation_space) == want]
        raise EvalError(f"Observability {obs!r} of {cfg.env} gives observations of shape {got}, but the network was "
                        f"trained on {cfg.observability!r} observations of shape {want}; choose one of: "
                        f"{', '.join(same)}.")
    return env.env if isinstance(env, AutoReset) else env


def memory_trace(carry):
    """A real vector of the memory's state, for pictures: every floating-point leaf of the carry, flattened, complex
    ones (a user's cell may have them) as their real then imaginary parts; of a Transformer-XL's cache, the newest
    cached input of its last layer. None without a memory."""
    if isinstance(carry, TrXLCarry):
        carry = carry.memory[-1, -1]
    leaves = []
    for x in jax.tree.leaves(carry):
        if jnp.issubdtype(x.dtype, jnp.complexfloating):
            leaves += [x.real.reshape(-1), x.imag.reshape(-1)]
        elif jnp.issubdtype(x.dtype, jnp.floating):
            leaves.append(x.reshape(-1))
    return jnp.concatenate(leaves).astype(jnp.float32) if leaves else None


def _check_obs_norm(run: LoadedRun) -> None:
    if missing_obs_norm(run):
        raise EvalError("The run normalised its observations, but its statistics were not saved with the model (a "
                        "run finished before obs_norm.eqx existed): its network cannot be given the inputs it "
                        "learned on.")


def _raw_state(state):
    while isinstance(state, TimeLimitState):
        state = state.env_state
    return state


def _act(model, obs_norm, env, state, obs, carry, start, key, t, greedy):
    """One step of one environment: the policy (as in training), then the environment."""
    k_act, k_env = jax.random.split(jax.random.fold_in(key, t))
    x = obs if obs_norm is None else obs_norm(obs)
    carry, action, _, values = policy_step(model, carry, x, start, k_act, greedy)
    new_state, ts = env.step(state, action, key=k_env)
    return carry, action, values, new_state, ts


def _play(model, obs_norm, env, keys, greedy: bool, max_steps: int):
    """One episode per key (vmapped) until every one has ended or `max_steps` steps."""
    n = keys.shape[0]
    k_reset, k_steps = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
    state, ts = jax.vmap(lambda k: env.reset(key=k))(k_reset)
    carry = jax.vmap(lambda _: model.init_carry())(jnp.arange(n))
    false = jnp.zeros((n,), bool)
    metrics = {k: jnp.zeros((n, len(names)), jnp.float32) for k, names in env.episode_metrics.items()}
    ep = EpisodeStats.zeros(n)
    stats = dict(ret=ep.ret, disc_ret=ep.disc_ret, discount=ep.discount, length=ep.length, terminated=false,
                 truncated=false, done=false, metrics=metrics)
    act = jax.vmap(_act, in_axes=(None, None, None, 0, 0, 0, 0, 0, None, None))

    def body(c):
        state, obs, carry, start, s, t = c
        carry, _, _, new_state, ts = act(model, obs_norm, env, state, obs, carry, start, k_steps, t, greedy)
        live = ~s["done"]
        ep = EpisodeStats(s["ret"], s["disc_ret"], s["discount"], s["length"]).add(ts.reward, env.gamma, live)
        info = {k: jnp.reshape(ts.info[k], (n, -1)).astype(jnp.float32) for k in s["metrics"]}
        s = dict(ret=ep.ret, disc_ret=ep.disc_ret, discount=ep.discount,
                 length=ep.length, terminated=s["terminated"] | (live & ts.terminated),
                 truncated=s["truncated"] | (live & ts.truncated), done=s["done"] | (live & ts.done),
                 metrics={k: jnp.where(live[:, None], info[k], m) for k, m in s["metrics"].items()})
        state = jax.vmap(tree_select)(live, new_state, state)
        obs = jax.vmap(tree_select)(live, ts.obs, obs)
        return state, obs, carry, jnp.zeros_like(start), s, t + 1

    def cond(c):
        return (c[5] < max_steps) & ~jnp.all(c[4]["done"])

    c = jax.lax.while_loop(cond, body, (state, ts.obs, carry, jnp.ones((n,), bool), stats, jnp.zeros((), jnp.int32)))
    return c[4]


def _jit(fn, cfg):
    return eqx.filter_jit(fn, compiler_options=compiler_options(cfg.deterministic, cfg.fast_compile) or None)


def _episode_keys(seed: int, episodes: int):
    check_seed(seed)
    return jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(episodes))


def _count(flag: str, v) -> int:
    """`v` as a count of at least 1 that the program can count (int32), else an EvalError naming `flag`."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 1 <= v <= INT32_MAX:
        raise EvalError(f"{flag} must be a positive integer of at most {INT32_MAX:,} (the program counts in int32), "
                        f"got {v!r}.")
    return int(v)


def _max_steps(env, max_steps: int | None) -> int:
    if max_steps is not None:  # the step counter of `_play`'s loop is int32
        return _count("--max-steps", max_steps)
    return int(env.max_steps_in_episode or 10_000)


@dataclasses.dataclass
class EvalResult:
    """What `evaluate` returns: one row per episode (`episodes`: hyperparameter set, seed index, episode, return,
    discounted return, length, how it ended, the environment's episode metrics), the `summary` (per set: mean and
    95% bootstrap CI over seeds of each seed's mean; per run: over its episodes) and the files written."""

    episodes: pd.DataFrame
    summary: dict
    files: list[Path]


def _stat(values) -> dict:
    mean, lo, hi = bootstrap_ci(np.asarray(values, np.float64))
    return {"mean": mean, "ci_low": lo, "ci_high": hi}


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
    environment's episode metrics; per set the mean and 95% bootstrap CI over seeds (of each seed's mean over its
    episodes; seeds whose training diverged are counted, `diverged`, and left out), per run the mean and 95%
    bootstrap CI over its episodes.

    The policy samples its actions (`greedy=True`: the most probable action). `observability` plays another
    observability of the same environment (observations must have the shape the network was trained on).
    Deterministic for a `seed`. Episodes still running after `max_steps` steps (default: the environment's time
    limit) are cut and counted in `cut`. With `save`, writes `eval-<observability>-<policy>-seed<seed>.json` (the
    summary) and `.csv` (the episodes) into `out` (default: the run directory); an existing evaluation of other
    settings or another model there is refused, not written over. A run trained in an environment given to
    `train(env=...)` plays that one (load it with `load_run(path, env=...)`), named by its classes and observability
    "given" in the summary and the files' names."""
    if not isinstance(greedy, bool | np.bool_):
        raise EvalError(f"greedy must be True or False, got {greedy!r}.")
    greedy = bool(greedy)
    if save and out is not None:  # (before anything is played)
        check_output_dir(Path(out), "eval writes its .json and .csv files", EvalError)
    run = load_run(run) if not isinstance(run, LoadedRun) else run
    cfg = run.config
    _count("--episodes", episodes)
    _check_obs_norm(run)
    if diverged_runs(run).all():  # (a model with non-finite parameters where training did not diverge: load_run's)
        raise EvalError(f"Every run of {str(run.path)!r} diverged in training: there is no policy to evaluate (its "
                        f"parameters are not finite); train it again, e.g. with a smaller --lr.")
    env = episode_env(run, observability)
    obs_name = "given" if run.trained_env[1] == "given" else observability or cfg.observability
    limit = _max_steps(env, max_steps)
    settings = dict(observability=obs_name, greedy=greedy, episodes=episodes, seed=seed, max_steps=limit)
    target = Path(out) if out is not None else run.path
    stem = f"eval-{obs_name}-{'greedy' if greedy else 'stochastic'}-seed{seed}"
    identity = {**settings, "model": run.source, "model_sha256": hashlib.sha256(serialise((run.model, run.obs_norm)))
                .hexdigest(), "run_dir": str(run.path.resolve()) if run.path else None}
    if save and target is not None:
        _check_not_overwriting(target / f"{stem}.json", identity)
    keys = _episode_keys(seed, episodes)
    play = _jit(lambda m, o, e, k: jax.vmap(lambda mm, oo: _play(mm, oo, e, k, greedy, limit))(m, o), cfg)
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
        lines.append("written: " + ", ".join(str(f) for f in result.files))
    return "\n".join(lines)


@dataclasses.dataclass
class Episode:
    """One recorded episode (`record_episode`): `views[t]` what the environment's drawer needs of the state before
    action t (and, last, of the final state: T + 1 entries), `actions`, `rewards`, `values` (critics) per step,
    `memory` (T, units) the memory's state after each step (None without a memory), how it ended."""

    views: object
    actions: np.ndarray
    rewards: np.ndarray
    values: np.ndarray
    memory: np.ndarray | None
    terminated: bool
    truncated: bool
    gamma: float

    @property
    def length(self) -> int:
        """Steps played."""
        return len(self.actions)

    @property
    def returns(self) -> tuple[float, float]:
        """(undiscounted, discounted) return."""
        return float(self.rewards.sum()), float(np.sum(self.rewards * self.gamma ** np.arange(self.length)))


def record_episode(run: LoadedRun, capture, *, env=None, index: int = 0, seed: int = 0, greedy: bool = False,
                   max_steps: int = 200) -> Episode:
    """Play one episode (episode 0 of `evaluate` with the same seed) with run `index` of `run` in `env` (default:
    `episode_env(run)`), keeping what `capture(raw_env, raw_state, obs)` takes of each state, the actions, rewards,
    values and the memory's state."""
    _check_obs_norm(run)
    env = episode_env(run) if env is None else env
    model, obs_norm = run.pick(index=index), run.pick_obs_norm(index=index)
    limit = min(_count("--steps", max_steps), _max_steps(env, None))
    raw_env = env.unwrapped

    def go(model, obs_norm, env, key):
        k_reset, k_steps = jax.random.split(key)
        state, ts = env.reset(key=k_reset)

        def body(c, t):
            state, obs, carry, start, done = c
            view = capture(raw_env, _raw_state(state), obs)
            carry, action, values, new_state, ts = _act(model, obs_norm, env, state, obs, carry, start, k_steps, t,
                                                        greedy)
            rec = dict(view=view, action=action, reward=jnp.where(done, 0.0, ts.reward), values=values,
                       memory=memory_trace(carry), ended=~done & ts.done, terminated=~done & ts.terminated)
            c = (tree_select(done, state, new_state), tree_select(done, obs, ts.obs), carry, jnp.asarray(False),
                 done | ts.done)
            return c, rec

        c0 = (state, ts.obs, model.init_carry(), jnp.asarray(True), jnp.asarray(False))
        c, recs = jax.lax.scan(body, c0, jnp.arange(limit))
        return recs, capture(raw_env, _raw_state(c[0]), c[1])

    recs, last = jax.device_get(_jit(go, run.config)(model, obs_norm, env, _episode_keys(seed, 1)[0]))
    ended = np.flatnonzero(recs["ended"])
    t = int(ended[0]) + 1 if len(ended) else limit
    views = jax.tree.map(lambda v, l: np.concatenate([np.asarray(v)[:t], np.asarray(l)[None]]), recs["view"], last)
    memory = None if recs["memory"] is None else np.asarray(recs["memory"])[:t]
    return Episode(views, np.asarray(recs["action"])[:t], np.asarray(recs["reward"])[:t],
                   np.asarray(recs["values"])[:t], memory, bool(recs["terminated"][:t].any()),
                   bool(len(ended) and not recs["terminated"][:t].any()), float(env.gamma))
