"""The training driver: every (hyperparameter set × seed) run of a configuration in one compiled program.

The device runs a chunk of updates as a `jax.lax.scan`, vmapped over runs; the host only sees chunk
boundaries, where it prints progress and writes the chunk's metrics. A configuration compiles once: the
numeric hyperparameters are array arguments, and the chunk's start is an array too.
"""

import dataclasses
import datetime
import math
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ..env import make, spec
from ..eval._results import RunDir
from ..eval._stats import auc, bootstrap_ci, final_value
from ._config import NUMERIC, Hyperparams, TrainConfig, validate
from ._ppo import TrainState, init_state, update

#: Number of times the chunk program was traced (compiled) in this process; tests use it.
TRACE_COUNT = 0


def default_unroll() -> int:
    return 1 if jax.default_backend() == "cpu" else 4


def structural(cfg: TrainConfig) -> TrainConfig:
    """The part of a configuration that shapes the compiled program (numeric values, seeds and logging
    are arguments, not part of the program)."""
    unroll = cfg.unroll if cfg.unroll is not None else default_unroll()
    return dataclasses.replace(cfg, **{k: () for k in NUMERIC}, seed=0, num_seeds=1, num_chunks=1, unroll=unroll)


@eqx.filter_jit
def _init(cfg: TrainConfig, env, keys):
    return jax.vmap(lambda k: init_state(cfg, env, k))(keys)


@eqx.filter_jit
def _chunk(cfg: TrainConfig, env, state: TrainState, hp: Hyperparams, start, chunk_len: int):
    global TRACE_COUNT
    TRACE_COUNT += 1

    def one_run(state, hp):
        zeros = jax.tree.map(
            lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(lambda s: update(cfg, env, s, hp)[1], state)
        )

        def body(state, i):
            # `start` is not batched, so this stays a real branch under vmap: the padding updates of the last
            # chunk cost nothing.
            return jax.lax.cond(
                start + i < cfg.num_updates, lambda s: update(cfg, env, s, hp), lambda s: (s, zeros), state
            )

        return jax.lax.scan(body, state, jnp.arange(chunk_len))

    return jax.vmap(one_run)(state, hp)


@dataclasses.dataclass
class TrainResult:
    """What `train` returns: the final state of every run, the metrics table and the summary."""

    config: TrainConfig
    state: TrainState
    metrics: pd.DataFrame
    summary: dict
    run_dir: Path | None
    compile_s: float
    steps_per_s: float


def default_out(cfg: TrainConfig) -> Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    agent = cfg.memory + ("-ld" if cfg.double_critic else "")
    return Path("runs") / f"{cfg.env}-{cfg.observability}-{agent}-{stamp}"


class _Progress:
    def __init__(self, enabled: bool, total: int):
        self.enabled, self.total = enabled, total
        self.tty = sys.stderr.isatty()

    def __call__(self, done_steps: int, sps: float, ret: float, disc: float, chunk: int, n_chunks: int):
        if not self.enabled:
            return
        msg = (f"[{chunk}/{n_chunks}] {done_steps:,}/{self.total:,} steps per run | {sps:,.0f} env steps/s | "
               f"return {ret:.3f} (discounted {disc:.3f})")
        print(("\r" + msg) if self.tty else msg, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self):
        if self.enabled and self.tty:
            print(file=sys.stderr)


def summarize(cfg: TrainConfig, metrics: pd.DataFrame) -> dict:
    """Per hyperparameter set, discounted and undiscounted: final returns (mean over the last 10% of updates per
    seed) and the area under the learning curve (`auc`), each as mean and 95% bootstrap CI over seeds. The
    best set by AUC of the discounted return (the paper's selection criterion) is `best_by_auc`."""
    sets = []
    for h, hp in enumerate(cfg.grid()):
        df = metrics[metrics.hp_index == h]
        row = {"hp_index": h, **hp}
        for col in ("return", "disc_return"):
            curves = [g.sort_values("update")[col].to_numpy() for _, g in df.groupby("seed")]
            finals = [final_value(c) for c in curves]
            mean, lo, hi = bootstrap_ci(finals)
            row[col] = {"mean": mean, "ci_low": lo, "ci_high": hi, "per_seed": finals}
            aucs = [auc(c) for c in curves]
            mean, lo, hi = bootstrap_ci(aucs)
            row[f"{col}_auc"] = {"mean": mean, "ci_low": lo, "ci_high": hi, "per_seed": aucs}
        sets.append(row)
    best = max(range(len(sets)), key=lambda i: -np.inf if np.isnan(sets[i]["disc_return_auc"]["mean"])
               else sets[i]["disc_return_auc"]["mean"])
    return {"env": cfg.env, "observability": cfg.observability, "memory": cfg.memory,
            "double_critic": cfg.double_critic, "num_seeds": cfg.num_seeds, "final_fraction": 0.1,
            "best_by_auc": best, "sets": sets}


def train(
    cfg: TrainConfig, out: str | Path | None = None, *, save: bool = True, progress: bool = True
) -> TrainResult:
    """Train every hyperparameter set × seed of `cfg` together. Writes a run directory unless `save=False`."""
    validate(cfg)
    env = make(cfg.env, cfg.observability, action_concat=cfg.action_concat)
    grid = cfg.grid()
    n_sets, n_seeds = len(grid), cfg.num_seeds
    hp_index = np.repeat(np.arange(n_sets), n_seeds)
    seed_index = np.tile(np.arange(n_seeds), n_sets)
    hp = Hyperparams.stack([grid[h] for h in hp_index])
    # Seed s uses the same key in every hyperparameter set: common random numbers make sets comparable.
    keys = jax.random.split(jax.random.key(cfg.seed), n_seeds)[seed_index]

    run_dir = None
    if save:
        run_dir = RunDir.create(out if out is not None else default_out(cfg))
        run_dir.write_config({
            "config": dataclasses.asdict(cfg),
            "hyperparameter_sets": grid,
            "env_spec": {"categories": spec(cfg.env).categories, "gamma": env.gamma,
                         "reference": spec(cfg.env).reference(cfg.observability)},
            "jax": jax.__version__, "device": str(jax.devices()[0].device_kind),
        })

    scfg = structural(cfg)
    state = _init(scfg, env, keys)
    num_updates = cfg.num_updates
    chunk_len = math.ceil(num_updates / min(cfg.num_chunks, num_updates))
    n_chunks = math.ceil(num_updates / chunk_len)
    steps_per_update = cfg.steps_per_update
    show = _Progress(progress, num_updates * steps_per_update)
    frames, chunk_times = [], []
    for c in range(n_chunks):
        start = c * chunk_len
        t0 = time.perf_counter()
        state, m = _chunk(scfg, env, state, hp, jnp.asarray(start, jnp.int32), chunk_len)
        m = jax.device_get(m)
        dt = time.perf_counter() - t0
        chunk_times.append(dt)
        n_valid = min(chunk_len, num_updates - start)
        df = _chunk_frame(m, n_valid, start, steps_per_update, hp_index, seed_index, grid)
        # Throughput of the chunk (all runs together; the first chunk includes compilation).
        df["steps_per_s"] = len(hp_index) * n_valid * steps_per_update / dt
        frames.append(df)
        if run_dir is not None:
            run_dir.write_chunk(c, df)
        runs = len(hp_index)
        show((start + n_valid) * steps_per_update, runs * n_valid * steps_per_update / dt,
             float(np.nanmean(df["return"])) if df["return"].notna().any() else float("nan"),
             float(np.nanmean(df["disc_return"])) if df["disc_return"].notna().any() else float("nan"),
             c + 1, n_chunks)
    show.close()

    metrics = pd.concat(frames, ignore_index=True)
    steady = chunk_times[1:] if len(chunk_times) > 1 else chunk_times
    per_update = float(np.median([t / chunk_len for t in steady]))
    compile_s = max(0.0, chunk_times[0] - per_update * chunk_len) if len(chunk_times) > 1 else float("nan")
    sps = len(hp_index) * steps_per_update / per_update
    summary = summarize(cfg, metrics)
    summary.update(compile_s=compile_s, steps_per_s=sps, wall_s=float(sum(chunk_times)))
    if run_dir is not None:
        run_dir.write_metrics(metrics)
        run_dir.save_model(state.model)
        run_dir.write_summary(summary)
    return TrainResult(cfg, state, metrics, summary, run_dir.path if run_dir else None, compile_s, sps)


def _chunk_frame(m: dict, n_valid: int, start: int, steps_per_update: int, hp_index, seed_index, grid) -> pd.DataFrame:
    runs = len(hp_index)
    upd = np.arange(start, start + n_valid)
    cols = {
        "hp_index": np.repeat(hp_index, n_valid),
        "seed": np.repeat(seed_index, n_valid),
        "update": np.tile(upd, runs),
        "env_step": np.tile((upd + 1) * steps_per_update, runs),
    }
    for k in NUMERIC:
        cols[k] = np.repeat([grid[h][k] for h in hp_index], n_valid)
    m = {k: np.asarray(v)[:, :n_valid].reshape(-1) for k, v in m.items()}
    episodes = m.pop("episodes")
    with np.errstate(invalid="ignore", divide="ignore"):
        cols["return"] = np.where(episodes > 0, m.pop("return_sum") / episodes, np.nan)
        cols["disc_return"] = np.where(episodes > 0, m.pop("disc_return_sum") / episodes, np.nan)
        cols["ep_length"] = np.where(episodes > 0, m.pop("length_sum") / episodes, np.nan)
    cols["episodes"] = episodes
    cols["lr_now"] = m.pop("lr")
    cols.update(m)
    return pd.DataFrame(cols)
