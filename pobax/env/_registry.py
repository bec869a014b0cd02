"""The environment registry: `make(name, observability=...)` and per-environment metadata.

Families are parameterised by their ID (`tmaze_{n}`); the paper's IDs are kept as they are. Each family
carries its categories of partial observability (paper §4), the paper's recommended general
hyperparameters, its best algorithm hyperparameters per agent where the paper reports them, and reference
values (e.g. T-Maze's optimal return).
"""

import dataclasses
import difflib
import re
from collections.abc import Callable
from typing import Any

from ._base import AbstractEnvironment
from ._wrappers import ActionConcat, AutoReset, TimeLimit


class UnknownEnvironmentError(ValueError):
    pass


@dataclasses.dataclass(frozen=True)
class EnvFamily:
    """A parameterised family of environments, e.g. `tmaze_{n}`."""

    template: str  # e.g. "tmaze_{length}"
    pattern: str  # regular expression with named groups, e.g. r"tmaze_(?P<length>\d+)"
    build: Callable[..., AbstractEnvironment]  # build(observability=..., **params, **overrides)
    observabilities: tuple[str, ...]
    categories: tuple[str, ...]
    max_steps: int | None
    registered: tuple[str, ...]  # the IDs used in the paper
    recommended: dict[str, Any] = dataclasses.field(default_factory=dict)
    best: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    reference: Callable[[AbstractEnvironment], dict[str, float]] | None = None
    extra: str | None = None  # pip extra that provides the dependencies, if any
    # The memory of the paper's ceiling agent (on `full`, else `perfect_memory`): a memoryless MLP in most
    # environments, a GRU where the paper used one (RockSample, Walker-V, HalfCheetah-V); None where the
    # ceiling is programmatic only (Battleship: the probability-search policy in `reference`).
    ceiling_memory: str | None = "memoryless"
    # Its observability: None for `full` where the family has it, else `perfect_memory`. RockSample's paper
    # ceiling is `perfect_memory` (the last reading of every rock) although it also offers `full`.
    ceiling_observability: str | None = None
    # The ceiling agent's observation encoder (`TrainConfig.encoder`): "auto" (the paper's rule) unless the
    # family's full observation is learned better through another (DMLab mazes: "flatten", see _families.py).
    ceiling_encoder: str = "auto"
    # How done episodes are reset during training: `AutoReset` (reset on the same step) unless the family
    # needs its own (e.g. a pool of pre-generated worlds where a reset is expensive).
    auto_reset: Callable[[AbstractEnvironment], AbstractEnvironment] = AutoReset

    def match(self, name: str) -> dict[str, Any] | None:
        m = re.fullmatch(self.pattern, name)
        if m is None:
            return None
        return {k: int(v) if v.isdigit() else v for k, v in m.groupdict().items()}


_FAMILIES: list[EnvFamily] = []


def register(family: EnvFamily) -> EnvFamily:
    _FAMILIES.append(family)
    return family


def registered_names() -> list[str]:
    """The registered environment IDs (the paper's), followed by the family templates."""
    names = [n for f in _FAMILIES for n in f.registered] + [f.template for f in _FAMILIES]
    return list(dict.fromkeys(names))  # a family of one ID has its ID as template: list it once


def _unknown(name: str) -> UnknownEnvironmentError:
    names = registered_names()
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.5)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return UnknownEnvironmentError(
        f"Unknown environment {name!r}.{hint} Known environments: {', '.join(names)}."
    )


def family_of(name: str) -> tuple[EnvFamily, dict[str, Any]]:
    """The family an ID belongs to and the parameters parsed from it."""
    for family in _FAMILIES:
        params = family.match(name)
        if params is not None:
            return family, params
    raise _unknown(name)


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Everything the library knows about one environment ID."""

    name: str
    family: EnvFamily
    params: dict[str, Any]

    @property
    def observabilities(self) -> tuple[str, ...]:
        return self.family.observabilities

    @property
    def categories(self) -> tuple[str, ...]:
        return self.family.categories

    @property
    def recommended(self) -> dict[str, Any]:
        return dict(self.family.recommended)

    @property
    def best(self) -> dict[str, dict[str, Any]]:
        return {k: dict(v) for k, v in self.family.best.items()}

    @property
    def ceiling_memory(self) -> str | None:
        return self.family.ceiling_memory

    @property
    def ceiling_encoder(self) -> str:
        return self.family.ceiling_encoder

    @property
    def ceiling_observability(self) -> str:
        if self.family.ceiling_observability is not None:
            return self.family.ceiling_observability
        return "full" if "full" in self.observabilities else "perfect_memory"

    def reference(self, observability: str = "partial") -> dict[str, float]:
        if self.family.reference is None:
            return {}
        return self.family.reference(make(self.name, observability, wrappers=False))


def spec(name: str) -> EnvSpec:
    family, params = family_of(name)
    return EnvSpec(name, family, params)


def make(
    name: str,
    observability: str = "partial",
    *,
    action_concat: bool = False,
    wrappers: bool = True,
    **overrides: Any,
) -> AbstractEnvironment:
    """Build a registered environment.

    With `wrappers=True` (the default) the environment is ready for training:
    `AutoReset(ActionConcat(TimeLimit(env)))` (the action concatenation only if `action_concat`).
    With `wrappers=False` it is the bare environment (no time limit, no auto-reset).
    `overrides` are passed to the environment's constructor (e.g. `map_seed=3`).
    """
    family, params = family_of(name)
    if observability not in family.observabilities:
        raise ValueError(
            f"Environment {name!r} has no observability {observability!r}; "
            f"it has: {', '.join(family.observabilities)}."
        )
    try:
        env = family.build(observability=observability, **params, **overrides)
    except TypeError as e:
        raise ValueError(f"Bad parameter for environment {name!r}: {e}") from None
    if not wrappers:
        return env
    if family.max_steps is not None:
        env = TimeLimit(env, family.max_steps)
    if action_concat:
        env = ActionConcat(env)
    return family.auto_reset(env)
