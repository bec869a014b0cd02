"""`validate`: a training configuration checked before anything is compiled, every refusal one line naming the flag
(counts the program indexes in int32, hyperparameters as trained in float32, the environment's options, the memory,
the combinations that cannot train)."""

import numpy as np

from ..env._base import check_seed
from ._config import _HINTS, INT32_MAX, NUMERIC, ConfigError, TrainConfig, _as_float, _shown, env_kwargs

_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: float32's smallest normal number: XLA flushes smaller magnitudes (subnormals) to zero on CPUs and GPUs.
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)


def _subnormal(name: str, given) -> str:
    return (f"--{name.replace('_', '-')} {_shown(given)} is below float32's smallest normal number (about 1.2e-38): "
            f"XLA computes with it as 0 (it flushes such values to zero), so it would train as 0; give a larger value.")
#: (low, high, low allowed) of each numeric hyperparameter; a step size above 1 is a typo (Adam's steps are of the
#: step size's order).
_BOUNDS = {
    "lr": (0.0, 1.0, False), "lambda0": (0.0, 1.0, True), "lambda1": (0.0, 1.0, True),
    "alpha": (0.0, 1.0, True), "ld_weight": (0.0, 1.0, True), "vf_coeff": (0.0, None, True),
    "entropy_coeff": (0.0, None, True), "clip_eps": (0.0, None, False), "max_grad_norm": (0.0, None, False),
}


def validate(cfg: TrainConfig) -> None:
    """Check a configuration before anything is compiled. Raises `ConfigError` with a one-line message."""
    from ..memory import memory_class  # noqa: PLC0415

    env_kwargs(cfg)
    try:  # a built-in name, or package.module:ClassName that imports and is a memory
        memory_class(cfg.memory)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    except SystemExit as e:  # the user's module ended the program while importing: nothing would train
        raise ConfigError(f"Memory {cfg.memory!r}: importing its module called sys.exit({e.code!r}); guard the "
                          f"module's script code with `if __name__ == \"__main__\":`.") from None
    for name in ("num_envs", "num_steps", "num_minibatches", "update_epochs", "total_steps", "hidden_size",
                 "num_seeds", "num_chunks", "embed_size", "num_heads", "num_layers", "qkv_features", "window_mem",
                 "window_grad", "rollout_unroll", "unroll"):
        v = getattr(cfg, name)
        if name == "total_steps" and not v >= 1:  # counted in updates below
            raise ConfigError(f"--total-steps must be a positive integer, got {v}.")
        if v is not None and not 1 <= v <= INT32_MAX and name != "total_steps":
            raise ConfigError(f"--{name.replace('_', '-')} must be a positive integer of at most {INT32_MAX:,} (the "
                              f"program counts in int32), got {v}.")
    try:  # a seed is 32 bits: a larger or negative one would train another seed's runs
        check_seed(cfg.seed)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.init == "release" and (cfg.memory not in ("memoryless", "gru")
                                  or cfg.encoder not in ("auto", "flatten", "mlp")):
        raise ConfigError(f"--init release is the original release's memoryless and GRU agents on vector observations "
                          f"(--memory memoryless or gru, --encoder auto, flatten or mlp), got --memory {cfg.memory} "
                          f"--encoder {cfg.encoder}; use --init ppo.")
    if cfg.num_envs % cfg.num_minibatches:
        raise ConfigError(
            f"--num-envs ({cfg.num_envs}) must be divisible by --num-minibatches ({cfg.num_minibatches}): "
            f"each minibatch holds whole environment sequences; e.g. use --num-minibatches "
            f"{max(d for d in range(1, cfg.num_minibatches + 1) if cfg.num_envs % d == 0)}."
        )
    if cfg.total_steps < cfg.steps_per_update:
        raise ConfigError(
            f"--total-steps ({cfg.total_steps}) is smaller than one update (--num-envs × --num-steps = "
            f"{cfg.steps_per_update}): raise --total-steps or lower --num-envs/--num-steps."
        )
    if cfg.num_updates > INT32_MAX:
        raise ConfigError(f"--total-steps {cfg.total_steps:,} is {cfg.num_updates:,} updates, more than the program "
                          f"counts (int32: {INT32_MAX:,}); lower --total-steps.")
    for name in NUMERIC:
        vals = getattr(cfg, name)
        if len(vals) == 0:
            raise ConfigError(f"--{name.replace('_', '-')} needs at least one value.")
    sets = int(np.prod([len(getattr(cfg, k)) for k in NUMERIC], dtype=object))
    seeds = f"--num-seeds {cfg.num_seeds:,}" + (f" × {sets:,} hyperparameter sets" if sets > 1 else "")
    rollout = f"--num-envs {cfg.num_envs:,} × --num-steps {cfg.num_steps:,} (one rollout)"
    for what, n in ((rollout, cfg.steps_per_update),
                    (f"{seeds} (the runs)", sets * cfg.num_seeds),
                    (f"{seeds} × --num-envs {cfg.num_envs:,} (environments stepped at once)",
                     sets * cfg.num_seeds * cfg.num_envs)):
        if n > INT32_MAX:
            raise ConfigError(f"{what} = {n:,} is more than the program can index (int32: {INT32_MAX:,}); lower it.")
    for name, (lo, hi, lo_ok) in _BOUNDS.items():
        def out(x, lo=lo, hi=hi, lo_ok=lo_ok) -> bool:
            return not np.isfinite(x) or x < lo or (x == lo and not lo_ok) or (hi is not None and x > hi)

        for given in getattr(cfg, name):
            v = _as_float(given)
            v32 = float(np.float32(v)) if np.isfinite(v) and abs(v) < _FLOAT32_MAX else float("inf")  # as trained
            if out(v) or out(v32):
                rng = (f"in {'[' if lo_ok else '('}{lo}, {hi}]" if hi is not None else
                       (f">= {lo}" if lo_ok else f"> {lo}")) + " and finite"
                why = "" if out(v) else f" ({v32:g} in float32, the precision it trains in)"
                raise ConfigError(f"--{name.replace('_', '-')} values must be {rng}, got {_shown(given)}{why}.")
            if 0 < abs(v32) < _FLOAT32_TINY:
                raise ConfigError(_subnormal(name, given))
        trained = [float(np.float32(_as_float(v))) for v in getattr(cfg, name)]
        if len(set(trained)) < len(trained):  # the same set trained twice: twice the work, no more information
            twice = next(v for v in trained if trained.count(v) > 1)
            raise ConfigError(f"--{name.replace('_', '-')} gives {twice:g} more than once (in float32, the precision "
                              f"it trains in): give each value once; --num-seeds sets the runs per value.")
    for name in (k for k, tp in _HINTS.items() if tp is float):  # e.g. --gating-bias
        v = _as_float(getattr(cfg, name))
        if not (np.isfinite(v) and abs(v) < _FLOAT32_MAX):
            raise ConfigError(f"--{name.replace('_', '-')} must be a finite number in float32, got "
                              f"{_shown(getattr(cfg, name))}.")
        if 0 < abs(float(np.float32(v))) < _FLOAT32_TINY:
            raise ConfigError(_subnormal(name, getattr(cfg, name)))
    if not float(np.float32(_as_float(cfg.reward_scale))) > 0:
        raise ConfigError(f"--reward-scale must be > 0 in float32 (it multiplies the rewards learnt from; float32 "
                          f"holds no positive number below about 1.4e-45), got {cfg.reward_scale}.")
    if cfg.memory == "trxl" and cfg.num_steps % cfg.window_grad:
        raise ConfigError(
            f"--num-steps ({cfg.num_steps}) must be a multiple of --window-grad ({cfg.window_grad}) for the "
            f"Transformer-XL memory: e.g. --window-grad "
            f"{max(d for d in range(1, min(cfg.window_grad, cfg.num_steps) + 1) if cfg.num_steps % d == 0)}."
        )
