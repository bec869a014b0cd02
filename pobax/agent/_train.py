"""The training loop: every (hyperparameter set × seed) run of a configuration in one compiled program.

    runs = Runs(cfg)                      # the environment, the runs' hyperparameters, their layout on the devices
    state = runs.init()                   # the initial training state of every run (one compiled program)
    for chunk in runs.chunks(state):      # `num_chunks` chunks of updates (another compiled program)
        chunk.metrics                     # a tidy table: one row per (hyperparameter set, seed, update)

A chunk is `jax.lax.scan` over updates, vmapped over runs (over several devices, each device its own runs:
`jax.shard_map`); the host sees only chunk boundaries. The numeric
hyperparameters and the chunk's first update are array arguments, so a configuration compiles once. Writing run
directories, checkpoints and summaries is `pobax.eval`'s (`pobax.eval.train` drives this loop).
"""

import dataclasses
import math
import time
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from .._backend import Backend, compiler_options
from .._distributed import fetch, put
from .._placement import default_devices
from ..env import AbstractEnvironment, spec
from ..env._wrappers import for_backend
from ._config import NUMERIC, ConfigError, Hyperparams, TrainConfig, make_env
from ._validate import validate
from ._ppo import TrainState, init_state, make_model, obs_normalizable, rollout_rows, update


def structural(cfg: TrainConfig, backend: Backend = Backend()) -> TrainConfig:
    """The part of a configuration that shapes the compiled program (numeric values, seeds and logging are
    arguments, not part of the program); the unroll factor resolved for `backend` (default: the CPU's)."""
    unroll = cfg.unroll if cfg.unroll is not None else backend.scan_unroll()
    return dataclasses.replace(cfg, **{k: () for k in NUMERIC}, seed=0, num_seeds=1, num_chunks=1, unroll=unroll)


def run_layout(cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """How the runs of `cfg` are ordered: run i trains the set `hp_index[i]` of `cfg.grid()` with the seed index
    `seed_index[i]`, each set's seeds next to each other."""
    n_sets = len(cfg.grid())
    return np.repeat(np.arange(n_sets), cfg.num_seeds), np.tile(np.arange(cfg.num_seeds), n_sets)


def run_hyperparams(cfg: TrainConfig) -> Hyperparams:
    """The numeric hyperparameters of `cfg`'s runs, stacked in `run_layout`'s order."""
    grid = cfg.grid()
    return Hyperparams.stack([grid[h] for h in run_layout(cfg)[0]])


def chunk_length(cfg: TrainConfig) -> int:
    """Updates per chunk: the run's updates split into at most `num_chunks` equal chunks (the last one padded)."""
    return math.ceil(cfg.num_updates / min(cfg.num_chunks, cfg.num_updates))


def _map_runs(fn, *args):
    """`fn` over the leading run axis of `args`: `jax.vmap`, or for one run `fn` of that run with the axis put back
    (the same computation without a batch dimension of 1 on every operation, which runs a little faster:
    `python benchmarks/bench_train.py --cases battleship_10:gru:1`)."""
    if jax.tree.leaves(args)[0].shape[0] == 1:
        return jax.tree.map(lambda x: x[None], fn(*jax.tree.map(lambda x: x[0], args)))
    return jax.vmap(fn)(*args)


def seed_keys(seed, num_seeds: int) -> jax.Array:
    """The keys of a configuration's seeds (`cfg.seed`, `cfg.num_seeds`): seed index i of every hyperparameter set
    starts from key i. (`seed` as uint32 inside the program: the same keys as `cfg.seed` on the host.)"""
    return jax.random.split(jax.random.key(seed), num_seeds)


def _init_runs(scfg: TrainConfig, backend: Backend, env, key_data: jax.Array | np.ndarray) -> TrainState:
    """Every run's initial state from its key's data (`Runs.key_data`). The program depends on the number of runs,
    not on how they split into sets and seeds: a rerun of as many runs as a sweep reuses the sweep's compilation."""
    return _map_runs(lambda k: init_state(scfg, env, k, backend), jax.random.wrap_key_data(key_data))


def _chunk_runs(fixed, state: TrainState):
    """`chunk_len` updates of every run from update `start` (updates past `cfg.num_updates` are skipped). With a
    mesh, each device trains its own runs (`jax.shard_map`): the runs never meet, and the compiler is not left to
    partition the batched program, which it did badly for convolutions batched over runs (all-gathers of the
    encoder's weights and activations on every step, 38 in a Craftax Transformer-XL chunk)."""
    cfg, backend, env, hp, start, chunk_len, mesh = fixed

    def local_runs(env, hp, start, state):
        def one_run(state, hp):
            def body(state, i):
                # `start` is not batched, so this stays a real branch under vmap: the padding updates of the last
                # chunk cost nothing. (Not `start + i`: near 2**31 updates that int32 sum wraps.)
                return jax.lax.cond(i < cfg.num_updates - start, lambda s: step(s), lambda s: (s, zeros), state)

            step = eqx.filter_closure_convert(lambda s: update(cfg, env, s, hp, batch, backend.gae()), state)
            zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), step.out_struct[1])
            return jax.lax.scan(body, state, jnp.arange(chunk_len))

        # The rows the vmaps give the rollout's layers (this device's runs), for their choice of product.
        batch = (rollout_rows(jax.tree.leaves(state)[0].shape[0], cfg.num_envs), backend.reduce_limit())
        return _map_runs(one_run, state, hp)

    if mesh is None:
        return local_runs(env, hp, start, state)
    env_arrays, env_static = eqx.partition(env, eqx.is_array)
    runs, replicated = jax.sharding.PartitionSpec("runs"), jax.sharding.PartitionSpec()
    per_device = jax.shard_map(
        lambda arrays, hp, start, state: local_runs(eqx.combine(arrays, env_static), hp, start, state),
        mesh=mesh, in_specs=(replicated, runs, replicated, runs), out_specs=runs, check_vma=False)
    return per_device(env_arrays, hp, start, state)


# The two programs, jitted once per set of XLA options (JAX caches their compilations).
_INIT: dict = {}
_CHUNK: dict = {}


def _program(table: dict, fn, options: dict, **kwargs):
    """`fn` jitted with these XLA options."""
    key = tuple(sorted(options.items()))
    if key not in table:
        table[key] = eqx.filter_jit(fn, compiler_options=options or None, **kwargs)
    return table[key]


@dataclasses.dataclass
class Chunk:
    """What one chunk of updates produced. `state` (every run's training state after the chunk) is valid until the
    next chunk is asked for: that chunk takes over its device buffers. With several processes its arrays span them
    (`pobax._distributed.fetch` gathers them); `metrics` holds every run's in every process."""

    index: int
    num_chunks: int
    state: TrainState
    metrics: pd.DataFrame
    seconds: float  # the chunk's wall time (the first one includes compiling the chunk program)
    env_steps: int  # environment steps of all runs in this chunk

    @property
    def steps_per_s(self) -> float:
        return self.env_steps / self.seconds


def check_given_env(env) -> None:
    """A ConfigError unless `env` (given to train in instead of a registered one) is a pobax environment that starts
    a new episode when one ends (its time steps carry `final_obs`, as `pobax.env.AutoReset` sets it): training
    rolls out a fixed number of steps, so an environment left in its terminal state would pay out again and again."""
    if not isinstance(env, AbstractEnvironment):
        raise ConfigError(f"env must be a pobax environment (pobax.env.make(...), or one of your own subclassing "
                          f"pobax.env.AbstractEnvironment), got {type(env).__name__}.")
    _, ts = eqx.filter_eval_shape(lambda k: env.reset(key=k), jax.random.key(0))
    if ts.final_obs is None:
        raise ConfigError(f"env ({type(env).__name__}) does not reset its episodes: training needs an environment "
                          f"that starts a new one when one ends; wrap it in pobax.env.AutoReset (pobax.env.make "
                          f"does, unless wrappers=False).")


class Runs:
    """The runs of a configuration: every hyperparameter set of `cfg.grid()` × `cfg.num_seeds` seeds, sharded over
    `devices` (default: `pobax._placement.default_devices`, as many devices as the runs' environments fill, every
    device of every process of a multi-process run; the batch is padded with copies of the last run to a multiple
    of the device count, and the copies never leave this class).

    The implementation choices of the programs (`backend`, `pobax._backend.Backend`) are resolved here, once, from
    the platform of `devices` and `cfg.backend`'s overrides, and passed down to the network and the environment.
    `env`: the environment to train in instead of `cfg.env`'s registered one (e.g. that one wrapped), with the same
    observation and action spaces; it must start a new episode when one ends (`check_given_env`)."""

    def __init__(self, cfg: TrainConfig, devices: list | None = None, env=None):
        validate(cfg)
        self.cfg = cfg
        runs = len(cfg.grid()) * cfg.num_seeds
        devs = default_devices(runs, cfg.num_envs, single_device=spec(cfg.env).single_device) if devices is None \
            else list(devices)
        try:
            self.backend = Backend.of(devs, cfg.backend)
        except ValueError as e:
            raise ConfigError(f"--backend: {e}") from None
        if env is None:
            env = make_env(cfg)
        else:
            check_given_env(env)
        self.env = for_backend(env, self.backend)
        # A network that cannot be built for this environment (an encoder for another observation, a memory's
        # constructor) fails here, before a run directory is written.
        eqx.filter_eval_shape(make_model, cfg, self.env, jax.random.key(0), self.backend)
        if cfg.normalize_obs and not obs_normalizable(self.env):
            raise ConfigError(
                f"--normalize-obs applies to vector observations; {cfg.env}'s {cfg.observability} observation is an "
                f"image, which the encoder scales itself: drop --normalize-obs.")
        self.grid = cfg.grid()
        self.hp_index, self.seed_index = run_layout(cfg)
        self.num_runs = len(self.hp_index)
        self.pad = (-self.num_runs) % len(devs)
        padded = np.concatenate([np.arange(self.num_runs), np.full(self.pad, self.num_runs - 1)])
        # Every (padded) run's starting key, as data: seed s starts from the same key in every hyperparameter set
        # (common random numbers make the sets comparable).
        keys = seed_keys(np.asarray(cfg.seed % 2**32, np.uint32), cfg.num_seeds)
        self.key_data = np.asarray(jax.random.key_data(keys))[self.seed_index[padded]]
        self.hp = Hyperparams.stack([self.grid[h] for h in self.hp_index[padded]])
        self.sharding = self.mesh = None
        if len(devs) > 1:
            self.mesh = jax.sharding.Mesh(np.array(devs), ("runs",))
            self.sharding = jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec("runs"))
            self.hp, self.key_data = put((self.hp, self.key_data), self.sharding)
        self.options = compiler_options(cfg.deterministic, cfg.fast_compile, platform=self.backend.platform)
        self.chunk_len = chunk_length(cfg)
        self.num_chunks = math.ceil(cfg.num_updates / self.chunk_len)

    def init(self) -> TrainState:
        """The initial training state of every run."""
        return jax.block_until_ready(self._init())

    def _init(self) -> TrainState:
        init = _program(_INIT, _init_runs, self.options)
        return self._unpad(init(self._structural(), self.backend, self.env, self.key_data))

    def template(self) -> TrainState:
        """The initial state's shapes and dtypes (`jax.ShapeDtypeStruct` leaves), computed without running it: what a
        checkpoint of these runs must match."""
        return jax.eval_shape(lambda: self._unpad(_init_runs(self._structural(), self.backend, self.env,
                                                             self.key_data)))

    def _structural(self) -> TrainConfig:
        return structural(self.cfg, self.backend)

    def _unpad(self, state: TrainState) -> TrainState:
        return jax.tree.map(lambda x: x[: self.num_runs], state) if self.pad else state

    def _pad(self, state: TrainState) -> TrainState:
        if self.pad:
            state = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], self.pad, axis=0)]), state)
        return put(state, self.sharding) if self.sharding is not None else state

    def fixed(self, start: int, chunk_len: int | None = None) -> tuple:
        """The chunk program's first argument for the chunk from update `start`: what shapes the program (the
        structural configuration, the backend, the environment, the chunk's length, the device mesh) and the runs'
        hyperparameters."""
        length = self.chunk_len if chunk_len is None else chunk_len
        return (self._structural(), self.backend, self.env, self.hp, np.asarray(start, np.int32), length, self.mesh)

    def chunk_program(self):
        """The jitted chunk program, called as `program(self.fixed(start), padded_state)`: the training state's
        buffers are donated."""
        return _program(_CHUNK, _chunk_runs, self.options, donate="all-except-first")

    def chunks(self, state: TrainState, first: int = 0, last: int | None = None) -> Iterator[Chunk]:
        """Train chunks `first` … `last - 1` (default: to the end) from `state` (the state after chunk `first - 1`),
        yielding each chunk's state and metrics. `state` is consumed: its buffers are donated to the first chunk."""
        if any(x.is_deleted() for x in jax.tree.leaves(state) if isinstance(x, jax.Array)):
            raise ValueError("Runs.chunks: this state was consumed by an earlier call (its buffers were donated to "
                             "the first chunk); continue from the state the last chunk yielded (`chunk.state`), or "
                             "start again from `runs.init()`.")
        chunk = self.chunk_program()
        cfg = self.cfg
        state = self._pad(state)
        last = self.num_chunks if last is None else min(last, self.num_chunks)
        for c in range(first, last):
            start = c * self.chunk_len
            t0 = time.perf_counter()
            state, m = chunk(self.fixed(start), state)
            m = jax.device_get(fetch(m))  # with several processes: every run's metrics, in each
            seconds = time.perf_counter() - t0
            n_valid = min(self.chunk_len, cfg.num_updates - start)
            yield Chunk(c, self.num_chunks, self._unpad(state), self._frame(m, start, n_valid), seconds,
                        self.num_runs * n_valid * cfg.steps_per_update)

    def _frame(self, m: dict, start: int, n_valid: int) -> pd.DataFrame:
        """The chunk's metrics as a tidy table: one row per (run, update), ordered by set, seed and update."""
        runs = self.num_runs
        upd = np.arange(start, start + n_valid)
        cols = {"hp_index": np.repeat(self.hp_index, n_valid), "seed": np.repeat(self.seed_index, n_valid),
                "update": np.tile(upd, runs), "env_step": np.tile((upd + 1) * self.cfg.steps_per_update, runs)}
        for k in NUMERIC:
            cols[k] = np.repeat([self.grid[h][k] for h in self.hp_index], n_valid)
        m = {k: np.asarray(v)[:runs, :n_valid].reshape(-1) for k, v in m.items()}
        episodes = m.pop("episodes")
        with np.errstate(invalid="ignore", divide="ignore"):
            cols["return"] = np.where(episodes > 0, m.pop("return_sum") / episodes, np.nan)
            cols["disc_return"] = np.where(episodes > 0, m.pop("disc_return_sum") / episodes, np.nan)
            cols["ep_length"] = np.where(episodes > 0, m.pop("length_sum") / episodes, np.nan)
            for k in [k for k in m if k.startswith("episode/")]:  # per-episode info (env.episode_metrics): mean
                cols[k.removeprefix("episode/")] = np.where(episodes > 0, m.pop(k) / episodes, np.nan)
        cols["episodes"] = episodes
        cols["lr_now"] = m.pop("lr")
        cols.update(m)
        # float64 throughout: a chunk read back from its CSV file is then identical to the one in memory (resume)
        return pd.DataFrame({k: np.asarray(v, np.float64) if np.asarray(v).dtype.kind == "f" else v
                             for k, v in cols.items()})
