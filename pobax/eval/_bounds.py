"""What a configuration asks of the machine, checked before anything is written or compiled: a lower bound on the
memory its runs need, against the memory of the devices they would run on.

The bound counts only what every run surely holds (the parameters, their gradient and Adam's two moments for the
width × width layers of the actor's and critics' heads and of a built-in memory (the GRU's six hidden × hidden input
and recurrent blocks, ...; one layer for a user's cell), and for a Transformer-XL its layers' projections; one
rollout's rewards, values,
log-probabilities and episode flags; one minibatch's activations; a Transformer-XL's cache of each environment), so
a refusal is never wrong; a configuration that passes may still not fit.
"""

import dataclasses
import math
import os

import jax

from ..agent import NUMERIC, ConfigError, TrainConfig

_FLOAT = 4  # bytes of a float32
#: The built-in memories' hidden × hidden weight blocks (their input is the encoder's hidden-wide output): the GRU's
#: three input and three recurrent gates, the LSTM's four and four, the memoryless MLP's three after its first; the
#: others' (and the Transformer-XL's, counted in embed_size) none surely of that size.
_SQUARE_BLOCKS = {"gru": 6, "lstm": 8, "memoryless": 3, "trxl": 0, "lru": 0, "s6": 0, "ffm": 0}


def device_memory(devices: list | None = None) -> tuple[int, str] | None:
    """(bytes, what) of the memory the runs can use: the machine's for CPU devices (which share it), else the sum of
    the devices' limits; None where the platform does not say."""
    devs = jax.devices() if devices is None else list(devices)
    if all(d.platform == "cpu" for d in devs):
        try:
            return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "this machine"
        except (ValueError, OSError, AttributeError):
            return None
    limits = [(d.memory_stats() or {}).get("bytes_limit") for d in devs]
    if not all(limits):
        return None
    return int(sum(limits)), f"{len(devs)} × {devs[0].device_kind}"


def train_bytes(cfg: TrainConfig) -> int:
    """A lower bound on the memory the runs of `cfg` need together (this module's docstring)."""
    runs = _sets(cfg) * cfg.num_seeds
    h = cfg.hidden_size
    if cfg.memory in _SQUARE_BLOCKS:  # the heads' hidden layers are the memory's width square, one per head
        width = cfg.embed_size if cfg.memory == "trxl" else h
        square = (2 + cfg.double_critic) * width ** 2 + _SQUARE_BLOCKS[cfg.memory] * h ** 2
    else:  # a user's cell: its output width is its own
        square = h ** 2
    params = 4 * square  # parameters, gradient, Adam's two moments
    rollout = cfg.num_envs * cfg.num_steps * (4 + cfg.hidden_size // cfg.num_minibatches)
    if cfg.memory == "trxl":  # per layer: query, key, value, position and output projections, the feed-forward pair
        params += 4 * cfg.num_layers * (5 * cfg.embed_size * cfg.qkv_features + 2 * cfg.embed_size ** 2)
        rollout += cfg.num_envs * cfg.num_layers * cfg.window_mem * cfg.embed_size  # each environment's cache
    return runs * (params + rollout) * _FLOAT


def _sets(cfg: TrainConfig) -> int:
    return math.prod(len(getattr(cfg, k)) for k in NUMERIC)


def check_fits(cfg: TrainConfig, devices: list | None = None) -> None:
    """Refuse (ConfigError, one line naming the flag to lower) a configuration whose runs cannot fit in the memory
    of `devices` (default: every device)."""
    have = device_memory(devices)
    need = train_bytes(cfg)
    if have is None or need <= have[0]:
        return
    default = TrainConfig()
    # the flag that, at its default, lowers the need most is the one to name
    candidates = {f"--{k.replace('_', '-')} {getattr(cfg, k)}": dataclasses.replace(cfg, **{k: getattr(default, k)})
                  for k in ("hidden_size", "num_seeds", "num_envs", "num_steps")
                  + (("embed_size", "qkv_features", "num_layers", "window_mem") if cfg.memory == "trxl" else ())}
    candidates[f"the {_sets(cfg):,} hyperparameter sets of the list-valued flags"] = \
        dataclasses.replace(cfg, **{k: getattr(cfg, k)[:1] for k in NUMERIC})
    flag = min(candidates, key=lambda f: train_bytes(candidates[f]))
    raise ConfigError(f"{flag}: the runs need at least {_gib(need)} of memory together, more than {have[1]} has "
                      f"({_gib(have[0])}); lower it.")


def check_eval_fits(episodes: int, cfg: TrainConfig, num_runs: int, devices: list | None = None) -> None:
    """Refuse `--episodes` that cannot be represented, or whose episodes (played side by side, every run at once)
    cannot fit in memory: each holds at least its memory's state and a few numbers."""
    if episodes > 2**31 - 1:
        raise ConfigError(f"--episodes {episodes:,} is more than the program can count (at most {2**31 - 1:,}).")
    have = device_memory(devices)
    need = episodes * num_runs * (cfg.hidden_size + 4) * _FLOAT
    if have is not None and need > have[0]:
        raise ConfigError(f"--episodes {episodes:,}: {num_runs} runs × that many episodes at once need at least "
                          f"{_gib(need)} of memory, more than {have[1]} has ({_gib(have[0])}); lower it.")


def _gib(n: int) -> str:
    return f"{n / 2**30:,.1f} GiB"


def _layout(tree) -> tuple:
    return jax.tree.structure(tree), [(x.shape, x.dtype) for x in jax.tree.leaves(tree)]


def check_user_memory(cfg: TrainConfig, env) -> None:
    """For a memory of the user's own (package.module:ClassName): the cell, built as the network builds it, holds
    only arrays (every other field static), returns real float outputs of the shape it declares, (time, out_size),
    for inputs of (time, in_size), and a carry laid out like its `init_carry()` — found out from the shapes alone,
    before anything compiles; else a ConfigError that names the cell and what is wrong. (An exception inside the
    cell's own code is the cell's: it propagates with its traceback.)"""
    if ":" not in cfg.memory:
        return
    import equinox as eqx  # noqa: PLC0415

    from ..agent._ppo import make_model  # noqa: PLC0415

    cell = eqx.filter_eval_shape(make_model, cfg, env, jax.random.key(0)).memory
    name = f"Memory {cfg.memory!r}: {type(cell).__name__}(in_size={cell.in_size}, hidden_size={cfg.hidden_size})"
    check = "Check the cell with pobax.memory.testing.check_memory(cell) before training."
    for path, leaf in jax.tree_util.tree_flatten_with_path(cell)[0]:
        if not isinstance(leaf, jax.ShapeDtypeStruct):  # (its arrays, as shapes)
            raise ConfigError(f"{name}: field {jax.tree_util.keystr(path)} is a {type(leaf).__name__}, not an array; "
                              f"mark every field that is not a JAX array eqx.field(static=True). {check}")
    time = 4
    xs = jax.ShapeDtypeStruct((time, cell.in_size), jax.numpy.float32)
    starts = jax.ShapeDtypeStruct((time,), jax.numpy.bool_)
    init, out = eqx.filter_eval_shape(lambda c, x, s: (c.init_carry(), c(c.init_carry(), x, s)), cell, xs, starts)
    if not (isinstance(out, tuple) and len(out) == 2):
        got = f"a tuple of {len(out)}" if isinstance(out, tuple) else f"a {type(out).__name__}"
        raise ConfigError(f"{name} returns {got} from __call__(carry, xs, starts); pobax needs (carry, ys). {check}")
    carry, ys = out
    if getattr(ys, "shape", None) != (time, cell.out_size):
        raise ConfigError(
            f"{name} returns outputs of shape {tuple(getattr(ys, 'shape', ()))} for inputs of shape "
            f"{(time, cell.in_size)}; pobax needs (time, out_size) = {(time, cell.out_size)}. {check}")
    if not jax.numpy.issubdtype(ys.dtype, jax.numpy.floating):
        raise ConfigError(f"{name} returns {ys.dtype} outputs; pobax needs real floats (the policy's gradient "
                          f"reaches the memory through them). {check}")
    if _layout(carry) != _layout(init):
        raise ConfigError(f"{name} returns a carry not laid out like its init_carry() (structure, shapes and dtypes "
                          f"must stay the same from step to step). {check}")
