"""The environment registry: `make(name, observability=...)` and per-environment metadata.

Families are parameterised by their ID (`tmaze_{n}`); the paper's IDs are kept as they are. Each family
carries its categories of partial observability (paper §4), the paper's recommended general
hyperparameters, its best algorithm hyperparameters per agent where the paper reports them, and reference
values (e.g. T-Maze's optimal return).
"""

import dataclasses
import difflib
import re
import types
import typing
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

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
    # ceiling is `perfect_memory` (the last reading of every rock) although it also offers `full`; the DMLab mazes'
    # is `perfect_memory` where the paper's is `full` (on the map maze 02's ceiling learned nothing:
    # docs/deviations.md).
    ceiling_observability: str | None = None
    # The ceiling agent's observation encoder (`TrainConfig.encoder`): "auto" (the paper's rule) unless the
    # family's full observation is learned better through another (DMLab mazes: "flatten", see _families.py).
    ceiling_encoder: str = "auto"
    # How done episodes are reset during training: `AutoReset` (reset on the same step) unless the family
    # needs its own (e.g. a pool of pre-generated worlds where a reset is expensive).
    auto_reset: Callable[[AbstractEnvironment], AbstractEnvironment] = AutoReset
    # Where `recommended` / `best` (what `--preset paper`, `gap` and `benchmark` use) differ from the paper's own
    # tables: {"recommended" or an agent key: {field: the paper's value}}. `paper_preset(..., original=True)` puts
    # them back; docs/deviations.md says why each differs and what measurement justified it.
    paper_original: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    # Budgets of `pobax benchmark` besides the generic `smoke` and `paper` (`budget()`): name -> dict of
    # `TrainConfig` fields (total_steps, num_seeds, ...).
    budgets: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    # The paper's results figure per benchmark agent (floor, gru, ld, trxl, ceiling), read off the figure
    # (about ±10%), on the scale of `paper_metric` ("disc_return", or "return" for undiscounted figures).
    paper_figure: dict[str, float] = dataclasses.field(default_factory=dict)
    paper_metric: str = "disc_return"
    # The paper's protocol for this family (`pobax benchmark --protocol paper`), where it differs from the defaults
    # (`EnvSpec.protocol`): "grid" and "ld_grid" (its sweep tables), "selection_seeds", "total_steps" (the steps of
    # its text), and "ceiling": the paper's ceiling agent as {"observability", "memory", "encoder"}, or
    # {"reference": KEY} where the paper's ceiling is a programmatic policy's value in `reference` (Battleship).
    paper_protocol: dict[str, Any] = dataclasses.field(default_factory=dict)
    # Whether a program's runs stay on one device unless the caller names several (`pobax._placement`): where
    # sharding them over devices fails (pixel MuJoCo: XLA's GPU compiler crashes, docs/performance.md).
    single_device: bool = False

    def match(self, name: str) -> dict[str, Any] | None:
        """The parameters of `name` if it is an ID of this family, else None: ASCII decimals without a leading zero
        as ints, the rest as strings. (Patterns take sizes as `(?:0|[1-9][0-9]*)`: one environment, one ID;
        `rocksample_015_15` would build rocksample_15_15's environment without its registry settings.)"""
        m = re.fullmatch(self.pattern, name, flags=re.ASCII)
        if m is None:
            return None
        return {k: int(v) if v.isdigit() and v == str(int(v)) else v for k, v in m.groupdict().items()}


_FAMILIES: list[EnvFamily] = []

#: Benchmark budgets, smallest first (`EnvSpec.budget`).
BUDGETS = ("smoke", "reduced", "paper")
#: The `smoke` budget, the same everywhere: three updates of small networks on 2 seeds (long enough for a Battleship
#: episode to end), compiled without XLA's backend optimisations. It tests that every agent of every environment
#: trains and reports end to end (in minutes on a CPU); its returns mean nothing.
SMOKE_BUDGET = dict(
    num_seeds=2, num_envs=4, num_steps=64, num_minibatches=2, update_epochs=1, total_steps=3 * 4 * 64, num_chunks=1,
    hidden_size=16, embed_size=16, num_heads=2, qkv_features=16, window_mem=32, window_grad=64, fast_compile=True,
)
#: Benchmark suites (`pobax benchmark --suite`): the discrete environments, the heavy ones (masked MuJoCo, pixel
#: MuJoCo, no-inventory Crafter), and the paper's benchmark (its results figure).
SUITES = {
    "discrete": ("tmaze_10", "rocksample_11_11", "rocksample_15_15", "battleship_10", "Navix-DMLab-Maze-01-v0",
                 "Navix-DMLab-Maze-02-v0", "Navix-DMLab-Maze-03-v0"),
    "heavy": ("Walker-V-v0", "HalfCheetah-V-v0", "Ant-V-v0", "Hopper-V-v0", "ant_pixels", "halfcheetah_pixels",
              "craftax_pixels"),
    "paper": ("tmaze_10", "rocksample_11_11", "rocksample_15_15", "battleship_10", "Walker-V-v0", "HalfCheetah-V-v0",
              "Navix-DMLab-Maze-01-v0", "Navix-DMLab-Maze-02-v0", "ant_pixels", "halfcheetah_pixels", "craftax_pixels"),
}


#: The paper's sweep for T-Maze, RockSample, Battleship and masked MuJoCo (appendix, non-λ-discrepancy table).
PAPER_GRID = {"lr": (2.5e-3, 2.5e-4, 2.5e-5, 2.5e-6), "lambda0": (0.1, 0.3, 0.5, 0.7, 0.9, 0.95)}
#: The paper's λ-discrepancy sweep (appendix, "hyperparameters swept across Lambda discrepancy algorithm").
PAPER_LD_GRID = {"lr": (2.5e-3, 2.5e-4, 2.5e-5), "lambda0": (0.1, 0.5, 0.95), "lambda1": (0.5, 0.7, 0.95),
                 "ld_weight": (0.25, 0.5)}
#: Seeds per set of the paper's sweeps (5; Battleship's 10 is in its family) and of its final runs.
PAPER_SELECTION_SEEDS = 5
PAPER_EVALUATION_SEEDS = 30


def discrepancy_terms(best: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The `best` of a family without a paper table of its own: a tabled member's λ-discrepancy terms (λ1 and β),
    without which its `ld` agent would have the defaults' β = 0, no discrepancy loss; everything else the defaults."""
    return {"ld": {k: best["ld"][k] for k in ("lambda1", "ld_weight")}}


def register(family: EnvFamily) -> EnvFamily:
    """Add `family` to the registry, after the families there (an ID is the first family's that matches it). A
    family whose template is taken, or one of whose IDs (`registered`) another family already builds, is refused:
    it would never be asked for them, and an ID never changes behaviour silently."""
    for other in _FAMILIES:
        taken = [n for n in family.registered if other.match(n) is not None]
        if other.template == family.template or taken:
            raise ValueError(f"Environment family {family.template!r}: "
                             + (f"{', '.join(map(repr, taken))} is already an ID of {other.template!r}" if taken else
                                "that template is already registered")
                             + "; give your family IDs of its own (e.g. a prefix: my_tmaze_{n}).")
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
    def single_device(self) -> bool:
        """A program's runs stay on one device unless the caller names several (`EnvFamily.single_device`)."""
        return self.family.single_device

    @property
    def ceiling_encoder(self) -> str:
        return self.family.ceiling_encoder

    @property
    def ceiling_observability(self) -> str:
        if self.family.ceiling_observability is not None:
            return self.family.ceiling_observability
        return "full" if "full" in self.observabilities else "perfect_memory"

    @property
    def paper_original(self) -> dict[str, dict[str, Any]]:
        return {k: dict(v) for k, v in self.family.paper_original.items()}

    @property
    def paper_figure(self) -> dict[str, float]:
        """The paper's figure values per agent, for the paper's own IDs (not for other members of the family)."""
        return dict(self.family.paper_figure) if self.name in self.family.registered else {}

    @property
    def paper_metric(self) -> str:
        return self.family.paper_metric

    def protocol(self) -> dict[str, Any]:
        """The paper's protocol for this environment: its sweep grids (`grid`, `ld_grid`), seeds per set of the
        sweep (`selection_seeds`) and of the final runs (`evaluation_seeds`), steps (`total_steps`), and its ceiling
        (`ceiling`: an agent {"observability", "memory", "encoder"}, or {"reference": KEY} for a programmatic
        policy's value among `reference()`'s). The ceiling defaults to the registry's (`ceiling_*`)."""
        p = self.family.paper_protocol
        ceiling = p.get("ceiling") or {"observability": self.ceiling_observability, "memory": self.ceiling_memory,
                                       "encoder": self.ceiling_encoder}
        return {"grid": dict(p.get("grid", PAPER_GRID)), "ld_grid": dict(p.get("ld_grid", PAPER_LD_GRID)),
                "selection_seeds": p.get("selection_seeds", PAPER_SELECTION_SEEDS),
                "evaluation_seeds": PAPER_EVALUATION_SEEDS,
                "total_steps": p.get("total_steps", self.family.recommended.get("total_steps", 1_500_000)),
                "ceiling": dict(ceiling)}

    def budget(self, name: str) -> dict[str, Any]:
        """The `TrainConfig` fields of a benchmark budget: `smoke` (a few updates of small networks, to test the
        machinery), the family's own (`reduced`: what the shipped results use), or `paper` (the paper's steps,
        30 seeds). A family without a `reduced` budget uses `paper`'s."""
        if name == "smoke":
            return dict(SMOKE_BUDGET)
        paper = dict(total_steps=self.family.recommended.get("total_steps", 1_500_000), num_seeds=30)
        if name == "paper":
            return paper
        if name in BUDGETS:
            return dict(self.family.budgets.get(name, paper))
        raise ValueError(f"Unknown budget {name!r}; choose among {', '.join(BUDGETS)}.")

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
    previous_action: str = "sampled",
    wrappers: bool = True,
    **overrides: Any,
) -> AbstractEnvironment:
    """Build a registered environment.

    With `wrappers=True` (the default) the environment is ready for training:
    `AutoReset(ActionConcat(TimeLimit(env)))` (the action concatenation only if `action_concat`; the action
    appended as the agent sampled it, `previous_action="sampled"`, or as the environment applies it, `"applied"`:
    clipped to the action space).
    With `wrappers=False` it is the bare environment (no time limit, no auto-reset).
    `overrides` are passed to the environment's constructor (e.g. `map_seed=3`), except `time_limit`: the
    `TimeLimit` wrapper's steps instead of the family's (`None`: no time limit).
    """
    if not isinstance(name, str):
        raise ValueError(f"make: the environment ID is a string such as 'tmaze_10' (`pobax envs` lists them), got "
                         f"{name!r}.")
    for flag, value in (("action_concat", action_concat), ("wrappers", wrappers)):
        if not isinstance(value, bool | np.bool_):
            raise ValueError(f"make: {flag} must be True or False, got {value!r}.")
    if previous_action not in ("sampled", "applied"):
        raise ValueError(f"previous_action must be 'sampled' or 'applied', got {previous_action!r}.")
    family, params = family_of(name)
    explicit = "time_limit" in overrides
    time_limit = overrides.pop("time_limit", family.max_steps)
    if observability not in family.observabilities:
        raise ValueError(
            f"Environment {name!r} has no observability {observability!r}; "
            f"it has: {', '.join(family.observabilities)}."
        )
    if clash := sorted(set(params) & set(overrides)):  # e.g. tmaze_5 with length=3: the ID names one environment
        raise ValueError(f"Bad parameter for environment {name!r}: {clash[0]} is set by the ID itself "
                         f"({family.template}); name the environment you want instead (`pobax envs` lists them).")
    if overrides:  # of the types the constructor declares, before it coerces them; lists and arrays as tuples
        _check_options(name, _env_class(family, observability, params), overrides)
        overrides = {k: _tuples(v) for k, v in overrides.items()}
    try:
        env = family.build(observability=observability, **params, **overrides)
    except (TypeError, OverflowError) as e:  # (an unknown option, or a number beyond what it is stored in)
        raise ValueError(f"Bad parameter for environment {name!r}: {e}") from None
    _CLASSES.setdefault((family.template, observability), type(env))
    if not wrappers:
        return env
    own = env.max_steps_in_episode  # the bare environment's own bound on an episode, if it has one
    if isinstance(time_limit, np.integer | np.ndarray | jax.Array) and np.ndim(time_limit) == 0 \
            and np.issubdtype(time_limit.dtype, np.integer):
        time_limit = int(time_limit)  # (a NumPy or JAX count, as a Python one)
    if not explicit and time_limit is not None and own is not None:  # (e.g. Craftax built with max_timesteps=5)
        time_limit = min(time_limit, own)
    if time_limit is not None and own is not None and not isinstance(time_limit, bool) \
            and isinstance(time_limit, int) and time_limit > own:
        raise ValueError(f"time_limit {time_limit:,} is longer than {name!r}'s episodes can be: the environment ends "
                         f"every episode within {own:,} steps itself; give at most {own:,}.")
    if time_limit is not None:
        env = TimeLimit(env, time_limit)
    if action_concat:
        env = ActionConcat(env, applied=previous_action == "applied")
    return family.auto_reset(env)


def _fits(value: Any, hint: Any) -> bool:
    """Whether an environment option's `value` is of its constructor's type `hint` as given, not as the constructor
    would coerce it (a float truncated to an int, `[true]` read as a length of 1, "yes" as true); a list stands for
    a tuple (JSON has no tuples). A hint this does not know passes (the constructor checks it)."""
    if isinstance(value, np.ndarray | jax.Array):  # from Python: an array stands for its numbers
        value = np.asarray(value).tolist()
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool | np.bool_)
    if hint is int:
        return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)
    if hint is float:
        return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)
    if hint is str:
        return isinstance(value, str)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0]) for v in value)
        return len(value) == len(args) and all(_fits(v, a) for v, a in zip(value, args))
    return True


def _tuples(value: Any) -> Any:
    """`value` with its lists and arrays (JSON's and NumPy's sequences) as tuples of Python numbers."""
    if isinstance(value, np.ndarray | jax.Array):
        value = np.asarray(value).tolist()
    return tuple(_tuples(v) for v in value) if isinstance(value, list | tuple) else value


#: A family's environment class per observability, from its first build in this process: the options' types.
_CLASSES: dict[tuple[str, str], type] = {}


def _env_class(family: EnvFamily, observability: str, params: dict) -> type | None:
    """The class `family` builds for `observability` (built once with its defaults to find it; None where that
    fails: the build with the options says why)."""
    key = (family.template, observability)
    if key not in _CLASSES:
        try:
            _CLASSES[key] = type(family.build(observability=observability, **params))
        except Exception:  # noqa: BLE001
            return None
    return _CLASSES[key]


def _check_options(name: str, cls: type | None, overrides: dict) -> None:
    """The options given to environment `name`'s constructor (of class `cls`) are of the types it declares, as
    given (`_fits`), else a one-line ValueError."""
    try:
        hints = typing.get_type_hints(cls.__init__) if cls is not None else {}
    except Exception:  # noqa: BLE001  (annotations it cannot resolve: the constructor's own checks stand)
        hints = {}
    for key, value in overrides.items():
        if key in hints and not _fits(value, hints[key]):
            shown = str(hints[key]).replace("typing.", "").replace("NoneType", "None")
            raise ValueError(f"Bad parameter for environment {name!r}: {key}={value!r} is not of its type {shown} "
                             f"(integers without a fraction, true/false for flags, lists for tuples).")
