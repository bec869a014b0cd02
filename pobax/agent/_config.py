"""Training configuration.

`TrainConfig` holds everything that defines a run. Sizes and switches are structural (a change recompiles);
the fields typed `tuple[float, ...]` are numeric hyperparameters: every combination of their values is one
hyperparameter set, and all sets × all seeds are trained together in one compiled, vmapped program.
"""

import dataclasses
import itertools
import json
import typing
from typing import Literal

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from .._paths import shown as _shown


#: numeric hyperparameters that can be swept inside one compiled program.
NUMERIC = ("lr", "lambda0", "lambda1", "alpha", "ld_weight", "vf_coeff", "entropy_coeff", "clip_eps", "max_grad_norm")


Encoder = Literal["auto", "flatten", "small_cnn", "full_cnn", "egocentric", "mlp"]
Init = Literal["ppo", "release"]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Configuration of a PPO training run (defaults: the paper's general hyperparameters)."""

    env: str = "tmaze_10"
    """Environment ID, e.g. tmaze_10 (see `pobax envs`)."""
    observability: str = "partial"
    """Observability variant: partial, perfect_memory or full (what the environment offers)."""
    env_options: tuple[str, ...] = ()
    """Arguments of the environment's constructor as KEY=VALUE (VALUE read as JSON where it parses, else as text),
    e.g. physics=positional (masked MuJoCo on Brax's positional pipeline, as the original implementation ran it) or
    map_seed=3. Part of the run's configuration, so recorded with it; empty: the registered environment. An option
    an environment does not take is refused before anything trains (`benchmark`: for every environment of the plan)."""
    memory: str = "gru"
    """Memory of the agent: memoryless, gru, trxl, a memory of the zoo (lstm, lru, s6, ffm; `pobax.memory.MEMORIES`),
    or your own cell as package.module:ClassName, built as ClassName(in_size, hidden_size, key=key)
    (docs/memories.md)."""
    action_concat: bool = False
    """Append the previous action to the observation."""
    previous_action: Literal["sampled", "applied"] = "sampled"
    """With action_concat and continuous actions, the previous action appended: as the policy sampled it
    (unbounded), or as the environment applied it (clipped to the action space, [-1, 1] for the MuJoCo robots)."""
    double_critic: bool = False
    """λ-discrepancy: two value heads trained with λ0 and λ1 returns, plus the discrepancy loss."""
    normalize_obs: bool = False
    """Normalise vector observations by a running mean and variance (per run, part of the training state); refused
    for image observations, which their encoder scales."""
    normalize_reward: bool = False
    """Scale rewards by the running standard deviation of the discounted return (per run; the logged returns
    stay unscaled). Value targets then have unit scale, which PPO's value clipping needs for MuJoCo rewards."""
    reward_scale: float = 1.0
    """Multiply the reward the agent learns from by this (before `normalize_reward`'s scaling; the logged returns
    stay unscaled), as Brax's PPO `reward_scaling`: with `normalize_advantages` off, the policy gradient's weight
    against the entropy bonus follows it."""
    normalize_advantages: bool = True
    """Normalise the advantages to zero mean and unit standard deviation within each minibatch (the usual PPO
    choice); off, the policy gradient keeps the advantages' own scale against the entropy bonus."""
    hidden_size: int = 128
    """Width of the network."""
    encoder: Encoder = "auto"
    """Observation encoder. auto: the paper's rule (vectors flattened; images SmallImageCNN up to 20 px a side,
    FullImageCNN above). flatten: any observation, images included, flattened into the memory's MLP. egocentric:
    an agent-centred map with heading channels (the DMLab mazes' full view) turned to the agent's heading, flattened.
    mlp: the flattened observation through three Dense → ReLU layers of `hidden_size`; before a GRU, the original
    release's four-layer embedding where the paper's listing has one Dense (`docs/parity.md`)."""
    extra_dense: bool = False
    """GRU only: an extra dense layer (2·hidden) before the GRU, as the paper's Battleship RNN."""
    init: Init = "ppo"
    """Initial weights. ppo: orthogonal, gain √2 on hidden layers, 0.01 on the policy's output, 1 on the value's.
    release: the original release's (PyPI pobax==0.0.1) as its saved parameters show (docs/parity.md): the first
    Dense ahead of the memory's output at gain 2, every later one at 0.01 (with four such layers the features reach
    the memory at 5e-7 of the scale ppo's gains give them), the heads' hidden layers at gain 2 (a continuous actor's
    √2), a GRU's input weights at standard deviation 1/√hidden. Memoryless and GRU agents; with --encoder mlp a GRU
    has the release's four-layer embedding."""
    num_envs: int = 4
    """Parallel environments per run (per seed and hyperparameter set)."""
    num_steps: int = 128
    """Rollout length per update."""
    num_minibatches: int = 4
    """Minibatches per epoch; each holds num_envs / num_minibatches whole environment sequences."""
    update_epochs: int = 4
    """Passes over each rollout."""
    total_steps: int = 1_500_000
    """Environment steps per run; the number of updates is total_steps // (num_envs * num_steps)."""
    anneal_lr: bool = True
    """Decay the learning rate linearly to 0 over training."""
    lr: tuple[float, ...] | float = (2.5e-4,)
    """Adam step size(s)."""
    lambda0: tuple[float, ...] | float = (0.95,)
    """GAE λ of the (first) critic."""
    lambda1: tuple[float, ...] | float = (0.5,)
    """GAE λ of the second critic (λ-discrepancy: read only with double_critic)."""
    alpha: tuple[float, ...] | float = (1.0,)
    """Policy advantage α·A^λ0 + (1 − α)·A^λ1 (λ-discrepancy: read only with double_critic)."""
    ld_weight: tuple[float, ...] | float = (0.0,)
    """β: weight of the λ-discrepancy loss (read only with double_critic)."""
    vf_coeff: tuple[float, ...] | float = (0.5,)
    """Value loss coefficient."""
    entropy_coeff: tuple[float, ...] | float = (0.01,)
    """Entropy bonus coefficient."""
    clip_eps: tuple[float, ...] | float = (0.2,)
    """PPO clipping ε (policy ratio and value)."""
    max_grad_norm: tuple[float, ...] | float = (0.5,)
    """Global gradient-norm clip."""
    num_seeds: int = 5
    """Seeds per hyperparameter set."""
    seed: int = 2020
    """Base random seed."""
    embed_size: int = 256
    """Transformer-XL embedding size."""
    num_heads: int = 8
    """Transformer-XL attention heads."""
    num_layers: int = 2
    """Transformer-XL layers."""
    qkv_features: int = 256
    """Transformer-XL query/key/value features."""
    window_mem: int = 128
    """Transformer-XL cached memory length."""
    window_grad: int = 64
    """Transformer-XL gradient window."""
    gating: bool = True
    """Transformer-XL GRU-style gating."""
    gating_bias: float = 2.0
    """Transformer-XL gating bias."""
    num_chunks: int = 20
    """Host round-trips per run: progress, metrics and checkpoints are written at chunk boundaries. At most the run's
    updates (a chunk holds at least one update: more chunks than updates train one update a chunk)."""
    unroll: int | None = None
    """Unroll factor of the GRU's and LSTM's time loops in the replay (forward and backward). Default: the
    platform's (`pobax._backend.default_unroll`: 1 on CPUs, 4 on accelerators, where fewer, larger kernels run
    faster). Compare: `python benchmarks/bench_train.py --cases rocksample_11_11:gru:1 --unroll 1 4`."""
    rollout_unroll: int = 1
    """Unroll factor of the rollout's time loop (environment step + network). Unrolling copies the environment's
    step into the program: faster steps on GPUs for a longer XLA compile. Compare: `python
    benchmarks/bench_train.py --cases tmaze_10:gru:30 --rollout-unroll 1 4` (env steps/s and compile seconds)."""
    deterministic: bool = False
    """On a GPU, the same seed trains the same run in every process on the same kind of GPU (XLA's deterministic
    ops, no autotuning by timing); costs throughput (docs/performance.md). CPUs are deterministic anyway."""
    fast_compile: bool = False
    """Compile with XLA's backend optimisations off: about 3× faster compiles on a CPU, slower steps. For tiny runs
    (the benchmark's smoke budget, tests)."""
    backend: str = ""
    """Implementation choices that replace the platform's (`pobax/_backend.py`), as comma-separated NAME=VALUE, e.g.
    gru_impl=dot,rollout_reduce_limit=0 (names: `pobax._backend.OVERRIDES`). Empty: the choices of the platform the
    runs train on. For comparing implementations (`benchmarks/bench_train.py --backend`): results agree up to float
    rounding, only speed differs."""

    def __post_init__(self):
        # a scalar hyperparameter is a one-element sweep: TrainConfig(lr=2.5e-3) means lr=(2.5e-3,); NumPy and JAX
        # numbers become Python's (as config.json writes and reads them back)
        for k in NUMERIC:
            given = getattr(self, k)
            if isinstance(given, np.ndarray | jax.Array) and given.ndim > 1:
                raise ConfigError(f"{k} is an array of shape {tuple(np.shape(given))}; give a number or a list (or "
                                  f"1-D array) of them, one per value swept.")
            v = _plain(getattr(self, k))
            object.__setattr__(self, k, tuple(map(_plain, v)) if isinstance(v, (list, tuple)) else (v,))
        for name in _HINTS:
            if name not in NUMERIC:
                object.__setattr__(self, name, _plain(getattr(self, name)))
        if isinstance(self.env_options, list):  # TrainConfig(env_options=["physics=positional"])
            object.__setattr__(self, "env_options", tuple(self.env_options))
        for name in _HINTS:  # TrainConfig's own fields (a subclass, e.g. a command line's, may add others)
            _check_type(name, getattr(self, name))

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        return self.total_steps // self.steps_per_update

    def grid(self) -> list[dict[str, float]]:
        """Every combination of the numeric hyperparameters, in a fixed order (the hyperparameter-set index)."""
        values = [getattr(self, k) for k in NUMERIC]
        return [dict(zip(NUMERIC, combo)) for combo in itertools.product(*values)]


class Hyperparams(eqx.Module):
    """Numeric hyperparameters as array leaves (scalars for one run; a leading axis for a batch of runs)."""

    lr: Float[Array, "*runs"]
    lambda0: Float[Array, "*runs"]
    lambda1: Float[Array, "*runs"]
    alpha: Float[Array, "*runs"]
    ld_weight: Float[Array, "*runs"]
    vf_coeff: Float[Array, "*runs"]
    entropy_coeff: Float[Array, "*runs"]
    clip_eps: Float[Array, "*runs"]
    max_grad_norm: Float[Array, "*runs"]

    @staticmethod
    def stack(rows: list[dict[str, float]]) -> "Hyperparams":
        return Hyperparams(**{k: jax.device_put(np.array([r[k] for r in rows], np.float32)) for k in NUMERIC})


class ConfigError(ValueError):
    """A configuration that cannot run; the message names the flag and the fix."""


def _is_real(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _check_type(name: str, value) -> None:
    """`value` has the type of the field `name` (the same check for flags, preset files, config.json and Python)."""
    tp = _HINTS[name]
    flag = f"--{name.replace('_', '-')}"
    if name in NUMERIC:
        bad = [v for v in value if not _is_real(v)]
        if bad:
            raise ConfigError(f"{flag} takes numbers, got {bad[0]!r}.")
        return
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple:  # tuple[str, ...]
        ok, want = isinstance(value, tuple) and all(isinstance(v, str) for v in value), "a list of strings"
    elif typing.get_origin(tp) is Literal:
        ok, want = value in args, "one of " + ", ".join(map(str, args))
    elif type(None) in args:  # int | None
        ok, want = value is None or (isinstance(value, (int, np.integer)) and not isinstance(value, bool)), \
            "an integer or null"
    elif tp is bool:
        ok, want = isinstance(value, (bool, np.bool_)), "true or false"
    elif tp is int:
        ok, want = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)), "an integer"
    elif tp is float:
        ok, want = _is_real(value), "a number"
    else:
        ok, want = isinstance(value, str), "a string"
    if not ok:
        raise ConfigError(f"{flag} must be {want}, got {value!r}.")


INT32_MAX = 2**31 - 1
def _as_float(v) -> float:
    """`v` as a float; an integer too large for one (10**400) as infinity, which the checks refuse."""
    try:
        return float(v)
    except OverflowError:
        return float("inf")


def _plain(v):
    """A NumPy or JAX number as Python's; an array of them as a tuple (a 0-d one as its number); else `v`."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (np.ndarray, jax.Array)):
        a = np.asarray(v)
        return a.item() if a.ndim == 0 else tuple(x.item() for x in a.ravel())
    return v


def _float_of(name: str, v):
    """A JSON integer where a float goes (field `name`), as that float; anything else as it is, for the type check."""
    if not isinstance(v, int) or isinstance(v, bool):
        return v
    if not np.isfinite(_as_float(v)):
        raise ConfigError(f"{name} is {_shown(v)}, too large for a float.")
    return float(v)


#: The names of `TrainConfig`'s fields.
FIELDS = frozenset(f.name for f in dataclasses.fields(TrainConfig))
_HINTS: dict = typing.get_type_hints(TrainConfig)


def config_values(values: dict, source: str | None = None, strict: bool = False) -> dict:
    """`TrainConfig` fields of a dict (a preset, or a configuration read back from JSON), type-checked as
    `TrainConfig` checks them: numeric hyperparameters become tuples (single values and JSON lists alike). Unknown
    keys are dropped, or with `strict` refused; errors name the `source` (e.g. "Preset file 'x.json'")."""
    unknown = sorted(set(values) - FIELDS)
    if unknown and strict:
        raise ConfigError(f"{source} has unknown fields: {', '.join(unknown)}.")
    out = {}
    for k, v in values.items():
        try:
            if k in NUMERIC:
                v = tuple(_float_of(k, x) for x in v) if isinstance(v, (list, tuple)) else (_float_of(k, v),)
            elif k == "env_options" and isinstance(v, list):  # JSON has no tuples
                v = tuple(v)
            elif k not in FIELDS:
                continue
            elif _HINTS[k] is float:
                v = _float_of(k, v)
            _check_type(k, v)
        except ConfigError as e:
            raise ConfigError(f"{source}: {e}" if source else str(e)) from None
        out[k] = v
    return out


def config_from_dict(values: dict, source: str | None = None) -> TrainConfig:
    """The configuration saved in a run directory's config.json (fields it lacks take their defaults); type errors
    name the `source`."""
    return TrainConfig(**config_values(values, source))


def _as_json(cfg: TrainConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def config_differences(saved: dict, cfg: TrainConfig) -> list[str]:
    """Fields in which a saved configuration (config.json's "config") differs from `cfg`. A field the saved
    one lacks (an option added since) counts as its default, which is the behaviour before the option."""
    return saved_config_differences(saved, _as_json(cfg))


def saved_config_differences(a: dict, b: dict) -> list[str]:
    """`config_differences` of two saved configurations: the fields in which they differ, a field either lacks
    counting as its default."""
    defaults = _as_json(TrainConfig())
    a, b = {**defaults, **a}, {**defaults, **b}
    return [k for k in defaults if a.get(k) != b.get(k)]


def env_kwargs(cfg: TrainConfig) -> dict:
    """`cfg.env_options` as the keyword arguments of the environment's constructor."""
    out = {}
    for item in cfg.env_options:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise ConfigError(f"--env-options takes KEY=VALUE items (e.g. physics=positional), got {item!r}.")
        if key in out:
            raise ConfigError(f"--env-options gives {key} twice ({item!r}); give each option once.")
        if key in _MAKE_ARGUMENTS:
            raise ConfigError(f"--env-options {item!r}: {key} is not an environment option but set by the "
                              f"training configuration ({_MAKE_ARGUMENTS[key]}).")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


#: `make`'s own arguments, which the configuration sets (never an environment's constructor option).
_MAKE_ARGUMENTS = {"name": "--env", "observability": "--observability", "action_concat": "--action-concat",
                   "previous_action": "--previous-action", "wrappers": "training always wraps the environment"}


def make_env(cfg: TrainConfig, observability: str | None = None):
    """The environment a run of `cfg` trains in (`observability`: another of its variants), wrapped for training:
    `cfg.env` with `cfg.env_options`, the previous action appended where `cfg.action_concat`."""
    from ..env import make  # noqa: PLC0415

    kwargs = env_kwargs(cfg)
    try:
        return make(cfg.env, observability or cfg.observability, action_concat=cfg.action_concat,
                    previous_action=cfg.previous_action, **kwargs)
    except ValueError as e:
        if not kwargs:
            raise
        raise ConfigError(f"--env-options {' '.join(cfg.env_options)}: {e}") from None
