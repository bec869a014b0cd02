"""Presets: the paper's settings per environment and agent, and preset files written by a sweep.

A preset is a dict of `TrainConfig` fields. `paper_preset` combines the environment's recommended general
settings (`spec(env).recommended`: num_envs, hidden_size, total_steps, entropy, embed size) with the paper's
best algorithm hyperparameters for the agent (`spec(env).best[agent]`, the "Best Hyperparameters" tables).
The agent key is `ld` for λ-discrepancy (`double_critic`), `full` for an agent on the `full` or
`perfect_memory` observation (the paper's ceiling), else the memory's name; a memory of the zoo or a user's cell
without a row of its own takes the GRU's (`gru`).

Preset files are JSON: `{"preset": {field: value, ...}, ...}` (any other keys are provenance); `sweep`
writes them (`best.json`, `pobax.eval.write_preset`) and `train --preset FILE` reads them.
"""

import dataclasses
import json
from pathlib import Path

from ..env import spec
from ..memory import PAPER_MEMORIES
from ._config import ConfigError, TrainConfig, config_values


def agent_key(memory: str, observability: str = "partial", double_critic: bool = False,
              best: dict | None = None) -> str:
    """The row of an environment's best hyperparameters (`best`, `spec(env).best`) for this agent (see the module
    docstring); with `best`, a memory beyond the paper's that has no row of its own gets the GRU's."""
    if double_critic:
        return "ld"
    if observability != "partial":
        return "full"
    if best is not None and memory not in best and memory not in PAPER_MEMORIES:
        return "gru"
    return memory


def paper_preset(env: str, memory: str = "gru", observability: str = "partial", double_critic: bool = False,
                 original: bool = False) -> dict:
    """The registry's settings for this environment and agent: the paper's recommended general settings and best
    hyperparameters, with the registry's documented deviations (`spec(env).paper_original`: where the paper's own
    settings did not show the gap here; the ceiling's encoder, `spec(env).ceiling_encoder`, is one). `original=True`
    gives the paper's tables as printed. Environments and agents without a table get the defaults."""
    s = spec(env)
    if observability not in s.observabilities:  # (any other name read as the ceiling's: "fully" gave its preset)
        raise ConfigError(f"paper_preset: {env} has no observability {observability!r}; choose among "
                          f"{', '.join(s.observabilities)}.")
    key = agent_key(memory, observability, double_critic, s.best)
    values = {**s.recommended, **s.best.get(key, {})}
    if key == "full" and s.ceiling_encoder != "auto":  # the encoder the ceiling reads its observation through
        values["encoder"] = s.ceiling_encoder
    if original:
        values.update({**s.paper_original.get("recommended", {}), **s.paper_original.get(key, {})})
    if double_critic:
        values["double_critic"] = True
    return config_values(values)


def load_preset(path: str | Path) -> dict:
    p = Path(path)
    if not p.exists():
        if p.is_symlink():  # (a link to nothing, or to itself: exists() is False for both)
            raise ConfigError(f"Preset file {str(p)!r} is a symbolic link that leads to nothing or back to itself; "
                              f"fix the link, or pass the file.")
        raise FileNotFoundError(f"Preset file {str(p)!r} does not exist; use --preset paper or a file written by `sweep`.")
    if not p.is_file():  # a FIFO or a device would be read until a writer closes it, or forever
        raise ConfigError(f"Preset file {str(p)!r} is not a regular file; pass a JSON file (as `sweep` writes).")
    try:
        data = json.loads(p.read_text())
    except UnicodeDecodeError:
        raise ConfigError(f"Preset file {str(p)!r} is not UTF-8 text; pass a JSON file (as `sweep` writes).") from None
    except RecursionError:
        raise ConfigError(f"Preset file {str(p)!r} nests too deeply to read; pass a JSON object of TrainConfig "
                          f"fields.") from None
    except ValueError as e:  # invalid JSON, or a number beyond what Python reads (4300 digits)
        raise ConfigError(f"Preset file {str(p)!r} is not valid JSON ({str(e).splitlines()[0]}).") from None
    values = data.get("preset", data) if isinstance(data, dict) else None
    if not isinstance(values, dict):
        raise ConfigError(f"Preset file {str(p)!r} must hold a JSON object of TrainConfig fields.")
    return config_values(values, source=f"Preset file {str(p)!r}", strict=True)


def resolve_preset(name: str, cfg: TrainConfig) -> dict:
    """`paper` (the registry's settings for cfg's environment and agent), `paper-original` (the paper's tables as
    printed, without the registry's deviations) or a preset file."""
    if name in ("paper", "paper-original"):
        key = agent_key(cfg.memory, cfg.observability, cfg.double_critic, spec(cfg.env).best)
        if key not in spec(cfg.env).best:
            raise ConfigError(f"--preset {name}: the paper has no hyperparameters for {cfg.env} with this agent "
                              f"({key}); drop --preset (defaults) or pass a preset file.")
        return paper_preset(cfg.env, cfg.memory, cfg.observability, cfg.double_critic, original=name != "paper")
    return load_preset(name)


def apply_preset(cfg: TrainConfig, preset: dict, keep: set[str] = frozenset()) -> TrainConfig:
    """`cfg` with the preset's values, except for the fields in `keep` (those set explicitly)."""
    return dataclasses.replace(cfg, **{k: v for k, v in preset.items() if k not in keep})
