"""Environment parity with the original implementation (PyPI `pobax==0.0.1`), under uniformly random actions.

    python benchmarks/parity.py --original-python /tmp/origvenv/bin/python \\
        --envs Walker-V-v0 Walker-P-v0 HalfCheetah-V-v0 HalfCheetah-P-v0 craftax_pixels:full=craftax \\
        --episodes 64 --num-envs 16 --json benchmarks/results/parity-heavy-cpu.json

For each pair it runs both implementations, each in a subprocess of its own (they share the import name `pobax`, so
never in one process): ours with `sys.executable` (`pobax.env.make`), the original with `--original-python`, an
interpreter of a separate virtual environment where `pobax==0.0.1` is installed. The original is used only through
its public API (`pobax.envs.get_env(name, key, num_envs)`, `env.reset`, `env.step`, `env.action_space(params)`);
its source is not read. Both workers run the same loop (this file, `--worker ours|original`): `--num-envs`
environments, actions drawn uniformly (discrete: uniform over the `n` actions; Box: uniform on [low, high]) by the
same code from the same keys, in `jax.lax.scan` chunks, until every environment has completed
`ceil(--episodes / --num-envs)` episodes or `--max-steps` steps have run (episodes still running then are left out
and counted as `cut_by_step_cap`). The first episodes of each environment are kept, so that long episodes are not
under-represented.

Compared (in this process, with numpy/scipy): episode return and length (mean, std, quantiles, two-sample
Kolmogorov-Smirnov statistic and p-value), per-dimension observation mean and std over every observation the agent
saw (the largest |difference of the means| in units of the pooled std, and the largest log-ratio of the stds),
observation shape and dtype, the action space, how episodes end (ours: `terminated` / `truncated` from `TimeLimit`;
the original: `done` only, with its `info` keys listed), whether a reset after an episode gives a new initial state,
and, for masked MuJoCo, which entries of the robot's full observation each masked observation keeps (found by running
the `-F-` ID with the same keys and actions and matching columns, so without reading the original's code). Where the
two keep different entries the observation statistics are compared on the entries both keep.

A pair is `OURS[:OBSERVABILITY][@PHYSICS][=ORIGINAL]`: our ID, its observability (default `partial`), our physics
setting for masked MuJoCo (`pobax.env.PHYSICS`, default: the pinned one), and the original's ID (default: the same
as ours). E.g. `Walker-V-v0@positional` runs ours on Brax's positional pipeline, `craftax_pixels:full=craftax`
compares our Craftax (symbolic view) with the original's `craftax` (Craftax-Symbolic-v1).

The original's factory wraps RockSample in a reward normaliser (`NormalizeVecReward`) that fails at reset in the
released package; the original's worker leaves that outermost wrapper out (`PEELED`, recorded as `peeled`), so that
RockSample's raw environment is compared, as every other pair's is.

The original's pixel MuJoCo (`ant_pixels`, `halfcheetah_pixels`) renders with Madrona (`madrona_mjx`), which is not
on PyPI: its `get_env` builds the Brax environment and then fails importing the renderer. For those IDs the original's
worker takes the environment `get_env` had built (from the failing call's frame), one wrapper below the renderer's,
vmaps it over the environments, and records the failure and the wrapper chain (`spec.below_renderer`): the dynamics
and state observation are compared (with ours at `:full`), not the frames.

The original's import needs a top-level module `definitions` (with `ROOT_DIR`) that its wheel does not ship, and it
calls `jax.tree_map`, which JAX 0.6 removed: the original's worker provides both (`ROOT_DIR`: the directory that
holds the installed `pobax` package; `jax.tree_map = jax.tree.map`) before importing it. Both are recorded in the
JSON (`original_shims`), with two more: `builtins.functools` (the original's pixel MuJoCo path names `functools`
without importing it) and `Observation.shape` (the reward normaliser its factory puts on RockSample reads
`obs.shape[0]` of the `Observation` tuple its environment returns, and fails at reset without it; `PEELED` still
leaves that normaliser out here, `benchmarks/original_agent.py --peel` with no names trains with it).
"""

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
# the original's outer wrappers left out of the comparison (by their `_env` attribute): its factory wraps RockSample
# in a reward normaliser even with normalize_env=False, and that wrapper fails at reset in the released package
PEELED = ("NormalizeVecReward",)
ORIGINAL_SHIMS = [
    "a module `definitions` with ROOT_DIR = the directory holding the installed pobax package (the wheel imports it "
    "but does not ship it)",
    "jax.tree_map = jax.tree.map (the original calls jax.tree_map, removed in JAX 0.6)",
    "builtins.functools = functools (get_env's pixel MuJoCo path names `functools` without importing it: NameError)",
    "Observation.shape = its .obs's shape (pobax.envs.wrappers.observation.Observation: the reward normaliser its "
    "factory puts on RockSample reads obs.shape[0] of that tuple and fails at reset without it)",
]


# ---------------------------------------------------------------------------------------------------------------
# Pairs
# ---------------------------------------------------------------------------------------------------------------


def parse_pair(text: str) -> dict:
    """`OURS[:OBSERVABILITY][@PHYSICS][=ORIGINAL]` -> {"label", "ours", "observability", "physics", "original"}."""
    left, _, original = text.partition("=")
    left, _, physics = left.partition("@")
    ours, _, observability = left.partition(":")
    if not ours:
        raise ValueError(f"Bad pair {text!r}: expected OURS[:OBSERVABILITY][@PHYSICS][=ORIGINAL].")
    return {"label": text, "ours": ours, "observability": observability or "partial", "physics": physics or None,
            "original": original or ours}


def is_masked_mujoco(name: str) -> bool:
    parts = name.split("-")
    return len(parts) == 3 and parts[1] in ("F", "P", "V") and parts[2] == "v0"


def full_id(name: str) -> str:
    robot, _, _ = name.split("-")
    return f"{robot}-F-v0"


# ---------------------------------------------------------------------------------------------------------------
# Statistics (used in the parent process)
# ---------------------------------------------------------------------------------------------------------------


def describe(x) -> dict:
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return {"n": 0}
    q = np.quantile(x, QUANTILES)
    return {"n": int(x.size), "mean": float(x.mean()), "std": float(x.std(ddof=1)) if x.size > 1 else 0.0,
            "min": float(x.min()), "max": float(x.max()),
            "quantiles": {f"q{int(p * 100):02d}": float(v) for p, v in zip(QUANTILES, q)}}


def compare_samples(a, b) -> dict:
    """Two samples (e.g. episode returns of ours and of the original): their descriptions, the difference of the
    means in units of the pooled std, and the two-sample Kolmogorov-Smirnov statistic and p-value (scipy; the
    exact distribution for small samples, asymptotic otherwise)."""
    from scipy import stats

    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    out = {"ours": describe(a), "original": describe(b)}
    if a.size == 0 or b.size == 0:
        out.update(ks_stat=None, ks_p=None, mean_diff_pooled_std=None)
        return out
    ks = stats.ks_2samp(a, b)
    pooled = math.sqrt(0.5 * (a.var(ddof=1 if a.size > 1 else 0) + b.var(ddof=1 if b.size > 1 else 0)))
    diff = float(a.mean() - b.mean())
    out.update(ks_stat=float(ks.statistic), ks_p=float(ks.pvalue),
               mean_diff_pooled_std=(diff / pooled) if pooled > 0 else (0.0 if diff == 0 else math.inf))
    return out


def compare_obs(mean_a, std_a, mean_b, std_b, eps: float = 1e-6) -> dict:
    """Per-dimension observation statistics of two implementations (same dimensions, same order): for each
    dimension the difference of the means in units of the pooled std, and log(std_a / std_b); their largest absolute
    values and where they are. Dimensions where both stds are below `eps` compare their means directly (0 if equal,
    inf otherwise)."""
    ma, sa, mb, sb = (np.asarray(v, np.float64).ravel() for v in (mean_a, std_a, mean_b, std_b))
    if not (ma.shape == sa.shape == mb.shape == sb.shape):
        raise ValueError(f"compare_obs: shapes differ: {ma.shape} {sa.shape} {mb.shape} {sb.shape}")
    pooled = np.sqrt(0.5 * (sa ** 2 + sb ** 2))
    const = pooled < eps
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(const, np.where(np.isclose(ma, mb, atol=eps), 0.0, np.inf), (ma - mb) / np.where(const, 1, pooled))
        log_ratio = np.where(const, 0.0, np.log(np.maximum(sa, eps) / np.maximum(sb, eps)))
    az, alr = np.abs(z), np.abs(log_ratio)
    i, j = int(np.argmax(az)), int(np.argmax(alr))
    return {"dims": int(ma.size), "max_abs_std_mean_diff": float(az[i]), "argmax_mean": i,
            "mean_abs_std_mean_diff": float(np.mean(az[np.isfinite(az)])) if np.isfinite(az).any() else math.inf,
            "max_abs_log_std_ratio": float(alr[j]), "argmax_std": j,
            "std_mean_diff": [float(v) for v in z], "log_std_ratio": [float(v) for v in log_ratio]}


# ---------------------------------------------------------------------------------------------------------------
# Workers (run in a subprocess: `--worker ours` with our venv, `--worker original` with the original's)
# ---------------------------------------------------------------------------------------------------------------


def _original_imports():
    """Import the original's `pobax.envs.get_env` (public API only), with the two shims of the module docstring."""
    import importlib.util
    import types

    spec = importlib.util.find_spec("pobax")
    if spec is None or spec.submodule_search_locations is None:
        raise ImportError("pobax (the original, 0.0.1) is not installed for this interpreter")
    pkg_dir = list(spec.submodule_search_locations)[0]
    if os.path.realpath(pkg_dir).startswith(os.path.realpath(REPO) + os.sep):
        raise RuntimeError(f"the original's worker would import our pobax ({pkg_dir}); use the original's venv")
    if "definitions" not in sys.modules:
        sys.modules["definitions"] = types.SimpleNamespace(ROOT_DIR=os.path.dirname(pkg_dir))
    import jax

    jax.tree_map = jax.tree.map
    import builtins
    import functools

    builtins.functools = functools
    from pobax.envs import get_env
    from pobax.envs.wrappers.observation import Observation

    if not hasattr(Observation, "shape"):
        Observation.shape = property(lambda self: self.obs.shape)

    return get_env


class _Ours:
    """Our environment, vmapped over environments (`pobax.env.make`: AutoReset(TimeLimit(env)))."""

    def __init__(self, name, observability, physics, num_envs):
        import jax

        import pobax.env as E

        overrides = {"physics": physics} if physics else {}
        self.env = env = E.make(name, observability, **overrides)
        self.E = E
        space = env.action_space
        if isinstance(space, E.Discrete):
            self.action = {"kind": "discrete", "n": int(space.n), "shape": [], "dtype": str(np.dtype(space.dtype))}
        else:
            self.action = {"kind": "box", "low": float(space.low), "high": float(space.high),
                           "shape": list(space.shape), "dtype": str(np.dtype(space.dtype))}
        osp = env.observation_space
        self.obs_space = repr(osp)
        self.time_limit = env.max_steps_in_episode
        self.names = getattr(env.unwrapped, "observation_names", None)
        self.info = {"observation_space": repr(osp), "time_limit": self.time_limit,
                     "time_limit_handling": "TimeLimit wrapper: `truncated` at max_steps (bootstrapped from "
                                            "final_obs), `terminated` by the environment; AutoReset outermost",
                     "physics": getattr(env.unwrapped, "physics", None), "env": repr(type(env.unwrapped).__name__)}
        self._reset = jax.vmap(lambda k: env.reset(key=k))
        self._step = jax.vmap(lambda s, a, k: env.step(s, a, key=k))

    def reset(self, keys):
        state, ts = self._reset(keys)
        return state, self.E.observation_array(ts.obs)

    def step(self, keys, state, actions):
        state, ts = self._step(state, actions, keys)
        extra = {"terminated": ts.terminated, "truncated": ts.truncated}
        return state, self.E.observation_array(ts.obs), ts.reward, ts.done, extra


class _Original:
    """The original's vectorized environment, through its public API only."""

    def __init__(self, name, num_envs, seed):
        import jax

        get_env = _original_imports()
        below_renderer = None  # set where the environment is one environment, vmapped here (get_env's step a batch)
        try:
            self.env, self.params = get_env(name, jax.random.PRNGKey(seed), num_envs=num_envs)
        except ModuleNotFoundError as e:
            if e.name != "madrona_mjx":
                raise
            # Pixel MuJoCo: get_env builds the Brax environment, then fails importing its renderer (Madrona, not
            # installable here). Compare the environment it had built, one level below the renderer's wrapper.
            built = _locals_of(e, "get_env")
            self.env, self.params = built["env"]._env, built["env_params"]
            below_renderer = {"error": f"ModuleNotFoundError: {e}", "wrappers": _wrapper_chain(self.env)}
        peeled = []
        while type(self.env).__name__ in PEELED:  # a reward normaliser only rescales what is compared here
            peeled.append(type(self.env).__name__)
            self.env = self.env._env
        space = self.env.action_space(self.params)
        n = getattr(space, "n", None)
        if n is not None:
            self.action = {"kind": "discrete", "n": int(n), "shape": list(getattr(space, "shape", ()) or ()),
                           "dtype": str(np.dtype(space.dtype))}
        else:
            self.action = {"kind": "box", "low": float(np.min(space.low)), "high": float(np.max(space.high)),
                           "shape": list(space.shape), "dtype": str(np.dtype(space.dtype))}
        try:
            osp = repr(self.env.observation_space(self.params))
        except Exception as e:  # noqa: BLE001
            osp = f"unavailable: {type(e).__name__}: {e}"
        limit = getattr(self.params, "max_steps_in_episode", None)
        self.names = None
        self.info = {"observation_space": osp, "time_limit": None if limit is None else int(limit),
                     "env_params": repr(self.params)[:400], "env": type(self.env).__name__, "peeled": peeled}
        if below_renderer:
            self.info["below_renderer"] = below_renderer
            self._reset = jax.vmap(self.env.reset, in_axes=(0, None))
            self._step = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))
        else:
            self._reset, self._step = self.env.reset, self.env.step

    @staticmethod
    def _obs(obs):
        return getattr(obs, "obs", obs)

    def reset(self, keys):
        obs, state = self._reset(keys, self.params)
        return state, self._obs(obs)

    def step(self, keys, state, actions):
        obs, state, reward, done, info = self._step(keys, state, actions, self.params)
        return state, self._obs(obs), reward, done, dict(info)


def _locals_of(error: BaseException, function: str) -> dict:
    """The local variables of the innermost frame of `function` in `error`'s traceback."""
    found, tb = None, error.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == function:
            found = tb.tb_frame.f_locals
        tb = tb.tb_next
    if found is None:
        raise RuntimeError(f"{function} is not in the traceback of {error!r}") from error
    return found


def _wrapper_chain(env) -> list[str]:
    """Type names from the outermost wrapper down (through `_env`), with a Brax environment's backend."""
    chain = []
    while env is not None and len(chain) < 20:
        backend = getattr(env, "_backend", None)
        chain.append(type(env).__name__ + (f" (backend {backend})" if isinstance(backend, str) else ""))
        env = getattr(env, "_env", None) if "_env" in vars(env) else None
    return chain


def _sample_actions(key, action, num_envs):
    import jax
    import jax.numpy as jnp

    if action["kind"] == "discrete":
        return jax.random.randint(key, (num_envs,), 0, action["n"], dtype=jnp.int32)
    lo, hi = action["low"], action["high"]
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"uniform actions need a bounded Box, got [{lo}, {hi}]")
    return jax.random.uniform(key, (num_envs, *action["shape"]), jnp.float32, lo, hi)


def _keys(seed):
    import jax

    return jax.random.split(jax.random.PRNGKey(seed), 2)  # (reset key, step key stream)


def run_episodes(adapter, num_envs, episodes_per_env, max_steps, chunk, seed, trace_steps=0) -> dict:
    """The common loop of both workers: see the module docstring."""
    import jax
    import jax.numpy as jnp

    k_reset, k_steps = _keys(seed)
    t0 = time.perf_counter()
    state, obs = adapter.reset(jax.random.split(k_reset, num_envs))
    obs = jnp.asarray(obs)
    first = obs  # each environment's first initial observation
    obs_shape, obs_dtype = list(obs.shape[1:]), str(obs.dtype)
    action = adapter.action

    def one(carry, k):
        state, obs, s1, s2 = carry
        k_act, k_env = jax.random.split(k)
        a = _sample_actions(k_act, action, num_envs)
        state, nobs, reward, done, extra = adapter.step(jax.random.split(k_env, num_envs), state, a)
        nobs = jnp.asarray(nobs)
        x = nobs.reshape(num_envs, -1).astype(jnp.float32)
        same_as_first = jnp.all((nobs == first).reshape(num_envs, -1), axis=1)
        out = {"reward": jnp.asarray(reward, jnp.float32), "done": jnp.asarray(done, bool),
               "same_as_first": same_as_first}
        for k_, v in extra.items():
            v = jnp.asarray(v)
            if v.shape == (num_envs,):
                out["x_" + k_] = v
        return (state, nobs, s1 + x.sum(0), s2 + (x * x).sum(0)), out

    @jax.jit
    def run_chunk(state, obs, key):
        zero = jnp.zeros(obs.reshape(num_envs, -1).shape[1:], jnp.float32)
        (state, obs, s1, s2), out = jax.lax.scan(one, (state, obs, zero, zero), jax.random.split(key, chunk))
        out["sum"], out["sumsq"] = s1, s2
        return state, obs, out

    x0 = np.asarray(obs.reshape(num_envs, -1), np.float64)
    s1, s2, count = x0.sum(0), (x0 ** 2).sum(0), num_envs
    ret = np.zeros(num_envs)
    length = np.zeros(num_envs, np.int64)
    done_eps = [[] for _ in range(num_envs)]
    ends = {"terminated": 0, "truncated": 0}
    info_returns, info_lengths = [], []
    starts_same, starts = 0, 0
    trace = {"obs": [np.asarray(obs[0], np.float64).ravel().tolist()], "reward": [], "done": []}
    steps, compile_s = 0, None
    info_keys = None
    while steps < max_steps and min(len(e) for e in done_eps) < episodes_per_env:
        key = jax.random.fold_in(k_steps, steps // chunk)
        tc = time.perf_counter()
        state, obs, out = run_chunk(state, obs, key)
        out = jax.tree.map(np.asarray, out)
        if compile_s is None:
            compile_s = time.perf_counter() - tc
        info_keys = info_keys or sorted(k_[2:] for k_ in out if k_.startswith("x_"))
        s1 += out["sum"].astype(np.float64)
        s2 += out["sumsq"].astype(np.float64)
        count += chunk * num_envs
        r, d = out["reward"], out["done"]
        for t in range(chunk):
            ret += r[t]
            length += 1
            if trace_steps and len(trace["reward"]) < trace_steps:
                trace["reward"].append(float(r[t, 0]))
                trace["done"].append(bool(d[t, 0]))
            for i in np.nonzero(d[t])[0]:
                if len(done_eps[i]) < episodes_per_env:
                    done_eps[i].append((float(ret[i]), int(length[i])))
                    if "x_terminated" in out:
                        ends["terminated"] += int(out["x_terminated"][t, i])
                        ends["truncated"] += int(out["x_truncated"][t, i] and not out["x_terminated"][t, i])
                    if "x_returned_episode" in out and out["x_returned_episode"][t, i]:
                        info_returns.append(float(out["x_returned_episode_returns"][t, i]))
                        info_lengths.append(int(out["x_returned_episode_lengths"][t, i]))
                    starts += 1
                    starts_same += int(out["same_as_first"][t, i])
                ret[i], length[i] = 0.0, 0
        steps += chunk
    mean = s1 / count
    std = np.sqrt(np.maximum(s2 / count - mean ** 2, 0.0))
    eps = [e for per_env in done_eps for e in per_env]
    return {
        "returns": [e[0] for e in eps], "lengths": [e[1] for e in eps],
        "episodes_per_env": [len(e) for e in done_eps],
        "cut_by_step_cap": int(sum(len(e) < episodes_per_env for e in done_eps)),
        "steps_per_env": steps, "observations": int(count),
        "obs_shape": obs_shape, "obs_dtype": obs_dtype, "obs_mean": mean.tolist(), "obs_std": std.tolist(),
        "action_space": action, "step_info_keys": info_keys,
        "episode_ends": ends if info_keys and "terminated" in info_keys else None,
        "info_episode_returns": info_returns or None, "info_episode_lengths": info_lengths or None,
        "restarts_equal_first_start": starts_same, "restarts": starts,
        "trace": trace if trace_steps else None,
        "compile_s": compile_s, "wall_s": time.perf_counter() - t0,
    }


def column_map(adapter_masked, adapter_full, num_envs, seed, steps=20) -> list | None:
    """For each column of the masked observation, the column of the full observation that holds the same numbers
    over `steps` random steps from the same keys and actions (None where no column matches, or where the full
    observation has several matching columns)."""
    import jax
    import jax.numpy as jnp

    k_reset, k_steps = _keys(seed)
    keys = jax.random.split(k_reset, num_envs)

    def rollout(adapter):
        def body(carry, t):
            state, _ = carry
            k_act, k_env = jax.random.split(jax.random.fold_in(k_steps, 10_000 + t))
            a = _sample_actions(k_act, adapter.action, num_envs)
            state, obs, *_ = adapter.step(jax.random.split(k_env, num_envs), state, a)
            obs = jnp.asarray(obs)
            return (state, obs), obs

        @jax.jit
        def run():
            state, obs = adapter.reset(keys)
            obs = jnp.asarray(obs)
            _, seen = jax.lax.scan(body, (state, obs), jnp.arange(steps))
            return jnp.concatenate([obs[None], seen])

        seen = np.asarray(run())
        return seen.reshape(-1, seen.shape[-1])

    m, f = rollout(adapter_masked), rollout(adapter_full)
    out = []
    for j in range(m.shape[1]):
        hits = [i for i in range(f.shape[1]) if np.allclose(m[:, j], f[:, i], atol=1e-6, rtol=0)]
        out.append(hits[0] if len(hits) == 1 else None)
    return out


def worker_main(args) -> None:
    import jax

    result = {"python": platform.python_version(), "jax": jax.__version__}
    try:
        import importlib.metadata as md

        for pkg in ("pobax", "pobax-bench", "brax", "mujoco", "mujoco-mjx", "craftax", "gymnax", "flax"):
            try:
                result.setdefault("packages", {})[pkg] = md.version(pkg)
            except md.PackageNotFoundError:
                pass
        if args.worker == "ours":
            adapter = _Ours(args.env, args.observability, args.physics, args.num_envs)
        else:
            adapter = _Original(args.env, args.num_envs, args.seed)
        result["spec"] = adapter.info
        result["obs_names"] = list(adapter.names) if adapter.names else None
        result.update(run_episodes(adapter, args.num_envs, args.episodes_per_env, args.max_steps, args.chunk,
                                   args.seed, trace_steps=args.trace_steps))
        if args.column_map and is_masked_mujoco(args.env):
            if args.worker == "ours":
                full = _Ours(args.env, "full", args.physics, args.num_envs)
                result["full_obs_names"] = list(full.names) if full.names else None
            else:
                full = _Original(full_id(args.env), args.num_envs, args.seed)
            result["column_map"] = column_map(adapter, full, args.num_envs, args.seed)
    except Exception as e:  # noqa: BLE001  (reported, not raised: the parent records what failed)
        import traceback

        result["error"] = f"{type(e).__name__}: {e}"
        result["traceback_tail"] = traceback.format_exc().splitlines()[-3:]
    with open(args.out, "w") as f:
        json.dump(result, f)


# ---------------------------------------------------------------------------------------------------------------
# Parent
# ---------------------------------------------------------------------------------------------------------------


def _spawn(python, which, env_name, pair, args, per_env, out_path, timeout):
    cmd = [python, os.path.abspath(__file__), "--worker", which, "--env", env_name, "--out", out_path,
           "--num-envs", str(args.num_envs), "--episodes-per-env", str(per_env), "--max-steps", str(args.max_steps),
           "--chunk", str(args.chunk), "--seed", str(args.seed), "--trace-steps", str(args.trace_steps)]
    if which == "ours":
        cmd += ["--observability", pair["observability"]]
        if pair["physics"]:
            cmd += ["--physics", pair["physics"]]
    if args.column_map:
        cmd += ["--column-map"]
    env = dict(os.environ)
    env.setdefault("JAX_PLATFORMS", "cpu")
    if which == "original":
        env.pop("PYTHONPATH", None)  # never let the original's interpreter see our checkout
    cwd = REPO if which == "ours" else tempfile.gettempdir()
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
        rc, tail = p.returncode, (p.stdout + p.stderr)[-1500:]
    except subprocess.TimeoutExpired:
        rc, tail = "timeout", f"timed out after {timeout} s"
    wall = time.perf_counter() - t0
    if os.path.exists(out_path):
        with open(out_path) as f:
            res = json.load(f)
    else:
        res = {"error": f"worker exited with {rc} and wrote nothing", "output_tail": tail}
    res["subprocess_wall_s"] = wall
    if rc != 0 and "error" not in res:
        res["error"] = f"worker exited with {rc}"
        res["output_tail"] = tail
    return res


def compare(pair, ours, orig) -> dict:
    row = {"pair": pair["label"], "ours_id": pair["ours"], "observability": pair["observability"],
           "physics": ours.get("spec", {}).get("physics") if isinstance(ours.get("spec"), dict) else None,
           "original_id": pair["original"]}
    for side, res in (("ours", ours), ("original", orig)):
        if "error" in res:
            row[f"{side}_error"] = res["error"]
    if "error" in ours or "error" in orig:
        for side, res in (("ours", ours), ("original", orig)):
            if "obs_shape" in res:
                row[f"{side}_obs"] = {"shape": res["obs_shape"], "dtype": res["obs_dtype"],
                                      "action_space": res["action_space"], "spec": res.get("spec")}
        return row
    row["returns"] = compare_samples(ours["returns"], orig["returns"])
    row["lengths"] = compare_samples(ours["lengths"], orig["lengths"])
    row["obs_shape"] = {"ours": ours["obs_shape"], "original": orig["obs_shape"]}
    row["obs_dtype"] = {"ours": ours["obs_dtype"], "original": orig["obs_dtype"]}
    row["action_space"] = {"ours": ours["action_space"], "original": orig["action_space"]}
    row["time_limit"] = {"ours": ours["spec"].get("time_limit"), "original": orig["spec"].get("time_limit")}
    row["restarts_equal_first_start"] = {s: f"{r['restarts_equal_first_start']}/{r['restarts']}"
                                         for s, r in (("ours", ours), ("original", orig))}
    if ours["obs_shape"] == orig["obs_shape"]:
        row["obs"] = compare_obs(ours["obs_mean"], ours["obs_std"], orig["obs_mean"], orig["obs_std"])
        row["obs"]["compared_on"] = "all dimensions"
    cm_o, cm_g = ours.get("column_map"), orig.get("column_map")
    if cm_o is not None and cm_g is not None:
        names = ours.get("full_obs_names")
        label = (lambda i: names[i] if names and i is not None and i < len(names) else i)
        row["kept_full_obs_entries"] = {"ours": [label(i) for i in cm_o], "original": [label(i) for i in cm_g],
                                        "ours_index": cm_o, "original_index": cm_g}
        common = [i for i in cm_o if i is not None and i in cm_g]
        row["kept_entries_equal"] = cm_o == cm_g
        if common and cm_o != cm_g:
            io, ig = [cm_o.index(i) for i in common], [cm_g.index(i) for i in common]
            sub = lambda r, idx, k: [r[k][j] for j in idx]  # noqa: E731
            c = compare_obs(sub(ours, io, "obs_mean"), sub(ours, io, "obs_std"), sub(orig, ig, "obs_mean"),
                            sub(orig, ig, "obs_std"))
            c["compared_on"] = f"the {len(common)} full-observation entries both keep: {[label(i) for i in common]}"
            row["obs"] = c
    tr_o, tr_g = ours.get("trace"), orig.get("trace")
    if tr_o and tr_g and len(tr_o["obs"][0]) == len(tr_g["obs"][0]):
        row["first_reset_obs_max_abs_diff"] = float(np.max(np.abs(np.subtract(tr_o["obs"][0], tr_g["obs"][0]))))
        n = min(len(tr_o["reward"]), len(tr_g["reward"]))
        if n:
            row["trace_reward_max_abs_diff"] = float(np.max(np.abs(np.subtract(tr_o["reward"][:n],
                                                                               tr_g["reward"][:n]))))
    return row


def _fmt(x, nd=1):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def _p(x):  # a p-value, or "-" where a side completed no episode
    return "-" if x is None else f"{x:.2g}"


def markdown(rows) -> str:
    lines = ["| pair | return ours | return original | KS p | length ours | length original | KS p | obs ours / "
             "original | max |Δmean|/σ | max |log σ ratio| |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "returns" not in r:
            ours = r.get("ours_error", "reset only" if "ours_obs" in r else "-")
            lines.append(f"| {r['pair']} | {ours} | {r.get('original_error', '-')} | | | | | | | |")
            continue
        R, L = r["returns"], r["lengths"]
        ob = r.get("obs", {})
        lines.append(
            f"| {r['pair']} | {_fmt(R['ours'].get('mean'))} ± {_fmt(R['ours'].get('std'))} | "
            f"{_fmt(R['original'].get('mean'))} ± {_fmt(R['original'].get('std'))} | {_p(R['ks_p'])} | "
            f"{_fmt(L['ours'].get('mean'))} ± {_fmt(L['ours'].get('std'))} | "
            f"{_fmt(L['original'].get('mean'))} ± {_fmt(L['original'].get('std'))} | {_p(L['ks_p'])} | "
            f"{r['obs_shape']['ours']} {r['obs_dtype']['ours']} / {r['obs_shape']['original']} "
            f"{r['obs_dtype']['original']} | {_fmt(ob.get('max_abs_std_mean_diff'), 2)} | "
            f"{_fmt(ob.get('max_abs_log_std_ratio'), 2)} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["Walker-V-v0", "Walker-P-v0", "HalfCheetah-V-v0", "HalfCheetah-P-v0"],
                   help="pairs OURS[:OBSERVABILITY][@PHYSICS][=ORIGINAL] (module docstring)")
    p.add_argument("--episodes", type=int, default=64, help="complete episodes per implementation and pair")
    p.add_argument("--num-envs", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=5000, help="steps per environment at most (cap for long episodes)")
    p.add_argument("--chunk", type=int, default=250, help="steps per compiled scan")
    p.add_argument("--trace-steps", type=int, default=50,
                   help="per-step rewards of environment 0 kept for a step-by-step comparison")
    p.add_argument("--no-column-map", dest="column_map", action="store_false",
                   help="skip finding which full-observation entries a masked MuJoCo observation keeps")
    p.add_argument("--original-python", default="/tmp/origvenv/bin/python",
                   help="an interpreter with pobax==0.0.1 installed (never our venv)")
    p.add_argument("--timeout", type=int, default=3600, help="seconds per worker")
    p.add_argument("--json", help="write the results here")
    # worker mode (internal)
    p.add_argument("--worker", choices=("ours", "original"), help=argparse.SUPPRESS)
    p.add_argument("--env", help=argparse.SUPPRESS)
    p.add_argument("--observability", default="partial", help=argparse.SUPPRESS)
    p.add_argument("--physics", default=None, help=argparse.SUPPRESS)
    p.add_argument("--episodes-per-env", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    p.add_argument("--column-map", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker_main(args)

    import jax

    per_env = math.ceil(args.episodes / args.num_envs)
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}; "
          f"original: {args.original_python}", flush=True)
    rows, raw = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, text in enumerate(args.envs):
            pair = parse_pair(text)
            res = {}
            # The original first: where it fails, ours only resets (its spaces and observation, no episodes).
            for which, python, name in (("original", args.original_python, pair["original"]),
                                        ("ours", sys.executable, pair["ours"])):
                out = os.path.join(tmp, f"{k}-{which}.json")
                spawn_args = args
                if which == "ours" and "error" in res["original"]:
                    spawn_args = argparse.Namespace(**{**vars(args), "max_steps": 0, "column_map": False})
                res[which] = _spawn(python, which, name, pair, spawn_args, per_env, out, args.timeout)
                r = res[which]
                if spawn_args is not args and "error" not in r:
                    r["note"] = "reset only: the original failed, no episodes were run"
                summary = (f"ERROR {r['error']}" if "error" in r else
                           f"{len(r['returns'])} episodes, {r['steps_per_env']} steps/env, "
                           f"compile {r['compile_s'] or 0:.1f}s, wall {r['subprocess_wall_s']:.0f}s")
                print(f"  {text} [{which}]: {summary}", flush=True)
            rows.append(compare(pair, res["ours"], res["original"]))
            raw[text] = {w: {k_: v for k_, v in r.items() if k_ not in ("obs_mean", "obs_std")} |
                         {"obs_mean": r.get("obs_mean") if len(r.get("obs_mean") or []) <= 64 else "omitted (>64)",
                          "obs_std": r.get("obs_std") if len(r.get("obs_std") or []) <= 64 else "omitted (>64)"}
                         for w, r in res.items()}
    md = markdown(rows)
    print(md)
    if args.json:
        versions = {w: {"python": r.get("python"), "jax": r.get("jax"), "packages": r.get("packages")}
                    for w, r in next(iter(raw.values())).items()} if raw else {}
        doc = {"command": "python " + " ".join([os.path.relpath(os.path.abspath(__file__), REPO)] + list(
                   sys.argv[1:] if argv is None else argv)),
               "device": f"{jax.devices()[0].device_kind} ({jax.default_backend()})", "host_cpus": os.cpu_count(),
               "versions": versions, "original_shims": ORIGINAL_SHIMS,
               "settings": {"episodes": args.episodes, "num_envs": args.num_envs, "episodes_per_env": per_env,
                            "max_steps": args.max_steps, "chunk": args.chunk, "seed": args.seed,
                            "actions": "uniform: discrete uniform over n, or uniform on [low, high] of the Box; the "
                                       "same code and keys in both workers"},
               "rows": rows, "raw": raw, "markdown": md}
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
