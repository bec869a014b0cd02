"""`load_run`: a run directory read back as Python objects (configuration, environment, trained models, metrics).

    run = pobax.load_run("runs/tmaze")      # a finished run (model.eqx) or an interrupted one (its checkpoint)
    run.model                               # every run's network, stacked: leading axis = run (set × seed)
    run.pick(set=0, seed=2)                 # one run's network
    run.metrics, run.summary                # the learning curves and the final returns
"""

import dataclasses
import os
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np
import pandas as pd

from ..agent import ActorCritic, ObsNorm, Runs, TrainConfig, config_from_dict, run_layout
from ..agent._ppo import obs_normalizable
from ..env import AbstractEnvironment
from ._args import as_path
from ._files import has_config, plain
from ._listing import missing_model, runs_below
from ._results import CheckpointError, RunDir
from ._given_env import given_env_mismatch, trained_env
from ._seal import sealed_files
from ._stats import summarize


class RunLoadError(ValueError):
    """A path that cannot be loaded as a run: missing, not a run directory, or holding no trained model yet."""


@dataclasses.dataclass
class LoadedRun:
    """A trained (or untrained) agent with everything needed to evaluate and watch it.

    `model` holds every run of the configuration stacked along a leading axis, in the order of `hp_index` and
    `seed_index` (run i trained hyperparameter set `hp_index[i]` with seed index `seed_index[i]`); `pick` takes one.
    `obs_norm` is the stacked observation normaliser when the runs normalised observations (else None). `source`
    says where the parameters came from (`model.eqx`, a checkpoint, or `untrained`); `chunks_done` is the chunks a
    checkpoint's parameters trained (None for `model.eqx`)."""

    config: TrainConfig
    env: AbstractEnvironment
    model: ActorCritic
    obs_norm: ObsNorm | None
    metrics: pd.DataFrame
    summary: dict
    path: Path | None = None
    finished: bool = True
    source: str = "model.eqx"
    record: dict = dataclasses.field(default_factory=dict)
    chunks_done: int | None = None

    @property
    def hp_index(self) -> np.ndarray:
        """The hyperparameter set of each run (leading axis of `model`)."""
        return run_layout(self.config)[0]

    @property
    def seed_index(self) -> np.ndarray:
        """The seed index of each run (leading axis of `model`)."""
        return run_layout(self.config)[1]

    @property
    def num_runs(self) -> int:
        """Runs in `model`: hyperparameter sets × seeds."""
        return len(self.hp_index)

    @property
    def hyperparameter_sets(self) -> list[dict]:
        """The numeric hyperparameters of each set, by set index."""
        return self.config.grid()

    @property
    def trained_env(self) -> tuple[str, str]:
        """The environment the runs trained in and its observability: the configuration's, or, for an environment
        given to `train(env=...)`, its classes and "given" (`pobax.eval._given_env.trained_env`)."""
        if isinstance(self.record.get("config"), dict):
            return trained_env(self.record)
        return self.config.env, self.config.observability

    @property
    def best_set(self) -> int:
        """The set with the largest area under the discounted learning curve (the summary's `best_by_auc`)."""
        return int(self.summary.get("best_by_auc", 0)) if self.summary else 0

    def index(self, set: int | None = None, seed: int = 0) -> int:  # noqa: A002  (the CLI's word)
        """The position in `model` of the run that trained set `set` (default: the best by AUC) with seed index
        `seed`."""
        for name, v in (("set", set), ("seed", seed)):
            if v is not None and (isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer))):
                raise RunLoadError(f"{name} must be an integer index, got {v!r}.")
        h = self.best_set if set is None else int(set)
        sets, seeds = len(self.config.grid()), self.config.num_seeds
        if not 0 <= h < sets:
            raise RunLoadError(f"Hyperparameter set {h} does not exist: the run has sets 0..{sets - 1}.")
        if not 0 <= seed < seeds:
            raise RunLoadError(f"Seed index {seed} does not exist: the run has seeds 0..{seeds - 1}.")
        return int(np.flatnonzero((self.hp_index == h) & (self.seed_index == seed))[0])

    def _position(self, set: int | None, seed: int, index: int | None) -> int:  # noqa: A002
        if index is not None and (isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer))):
            raise RunLoadError(f"index must be an integer, got {index!r}.")
        i = self.index(set, seed) if index is None else int(index)
        if not 0 <= i < self.num_runs:
            raise RunLoadError(f"Run index {i} does not exist: the run holds {self.num_runs} runs.")
        return i

    def pick(self, set: int | None = None, seed: int = 0, *, index: int | None = None) -> ActorCritic:  # noqa: A002
        """One run's network (unbatched): by `index` into `model`, else by hyperparameter set and seed index."""
        return _take(self.model, self._position(set, seed, index))

    def pick_obs_norm(self, set: int | None = None, seed: int = 0, *,  # noqa: A002
                      index: int | None = None) -> ObsNorm | None:
        """One run's observation normaliser (None when observations were not normalised), picked as `pick` picks."""
        i = self._position(set, seed, index)
        return None if self.obs_norm is None else _take(self.obs_norm, i)

    @classmethod
    def untrained(cls, cfg: TrainConfig) -> "LoadedRun":
        """The networks of `cfg` as training initialises them (same seeds), untrained, as a run to evaluate or
        render: a baseline, or a quick look at an environment and its pictures without training. Observation
        statistics, if `cfg` normalises observations, are the initial ones (zero mean, unit variance)."""
        runs = Runs(cfg)  # validates cfg
        state = runs.init()  # the training loop's own initialisation
        return cls(cfg, runs.env, state.model, state.obs_norm, _empty_metrics(), {}, None, False, "untrained")


def _take(tree, i: int):
    return jax.tree.map(lambda x: x[i] if eqx.is_array(x) else x, tree)


def _empty_metrics() -> pd.DataFrame:
    return pd.DataFrame(columns=["hp_index", "seed", "update", "env_step", "return", "disc_return"])


def _read_config(path: Path) -> tuple[dict, TrainConfig]:
    record = RunDir(path).read_config()
    if not isinstance(record, dict) or not isinstance(record.get("config"), dict):
        raise RunLoadError(f"{str(path / 'config.json')!r} is not a run configuration pobax wrote (no 'config').")
    return record, config_from_dict(record["config"], source=repr(str(path / "config.json")))


#: `load_run`'s summary before it is read (`None` is a summary.json holding null).
_UNREAD = object()


def load_run(path: str | os.PathLike, *, env: AbstractEnvironment | None = None) -> LoadedRun:
    """Load a run directory written by `pobax.train` / `pobax train`: its configuration (`TrainConfig`), its
    environment, every run's trained network (stacked; `pick` one), the observation normaliser if any, the metrics
    table and the summary. A finished run loads `model.eqx`; an interrupted one its latest checkpoint (`finished` is
    False; the metrics and the summary cover the chunks that checkpoint has trained). A run trained in an environment
    given to `train(env=...)` loads with that environment (`env`), never silently with the registered one or with
    another (its classes and parameters are checked: `env_digest`). Raises
    `RunLoadError` (a ValueError) with a one-line message for a missing path, a directory that is not a run, a
    configuration edited after its run finished, or a run with no trained model yet; `path` may start with `~`."""
    p = as_path("load_run", "path", path, RunLoadError, what="a run directory's path")
    if not p.exists():
        raise RunLoadError(f"{str(p)!r} does not exist: pass a run directory (see `pobax results`).")
    try:
        marked = p.is_dir() and has_config(p)
    except CheckpointError as e:  # config.json a link to nothing or to itself, a FIFO, a directory beside run files
        raise RunLoadError(str(e).splitlines()[0]) from None
    if not marked:
        below = runs_below(p)
        raise RunLoadError(f"{str(p)!r} is not a run directory (no config.json)" + (below + "." if below else
                           ": pass a directory written by `pobax train` (see `pobax results`)."))
    rd = RunDir(p)
    sealed = _UNREAD  # (a summary.json holding null reads as None)

    def ended() -> bool:  # what the run's end leaves (a run that finished while it was read is read again, as
        # finished, through its seal); not a summary.json alone, beside a checkpoint it cannot read: read again forever
        return os.path.lexists(p / "summary.json") and os.path.lexists(p / "model.eqx")

    try:
        if ended():
            sealed = rd.read_summary()  # its seal checked first: it also covers config.json
        record, cfg = _read_config(p)
        given = given_env_mismatch(record, env)
        if given:
            raise RunLoadError(f"{str(p)!r} was {given}: pass load_run(..., env=) the environment it trained in.")
        runs = Runs(cfg, env=env)  # (validates cfg)
    except (CheckpointError, ValueError) as e:
        msg = str(e).splitlines()[0]
        raise RunLoadError(msg if str(p) in msg else f"{str(p / 'config.json')!r}: {msg}") from None
    if not os.path.lexists(p / "summary.json"):  # unfinished: read only what a resume would continue
        try:
            rd.check_unfinished()
        except CheckpointError as e:
            if ended():  # it finished while it was read, and cleared its checkpoint
                return load_run(p, env=env)
            raise RunLoadError(str(e).splitlines()[0]) from None
    template = runs.template()  # every run's training state, as shapes: what model.eqx and a checkpoint are read into
    obs_norm = None
    if ended():  # finished (summary.json: last)
        finished, source = True, "model.eqx"
        def unreadable(name: str, e: Exception) -> RunLoadError:  # a damaged file, or another configuration's
            return RunLoadError(f"{str(p / name)!r} is damaged or does not match the run's configuration "
                                f"({str(e).splitlines()[0] if str(e) else type(e).__name__}); restore it, or train "
                                f"the run again.")

        try:
            model = rd.load_model(template.model)
        except Exception as e:  # noqa: BLE001
            raise unreadable("model.eqx", e) from None
        if not os.path.lexists(p / "obs_norm.eqx") and "obs_norm.eqx" in sealed_files(p):
            raise RunLoadError(f"{str(p / 'obs_norm.eqx')!r} is missing: the run finished with it (its SHA-256 in "
                               f"summary.json) and its model needs it; restore it, or train the run again.")
        if os.path.lexists(p / "obs_norm.eqx"):  # (a FIFO or a broken link there is damage, not "none")
            try:
                obs_norm = eqx.tree_deserialise_leaves(plain(p / "obs_norm.eqx"), template.obs_norm)
            except Exception as e:  # noqa: BLE001
                raise unreadable("obs_norm.eqx", e) from None
        try:
            metrics = rd.metrics()
        except FileNotFoundError:
            metrics = _empty_metrics()
        except CheckpointError as e:  # a damaged metrics table (read_metrics)
            raise RunLoadError(str(e).splitlines()[0]) from None
    elif os.path.lexists(p / "checkpoint.json"):
        finished = False
        try:
            state, done = rd.load_checkpoint(template)
            # the chunks the checkpointed state has trained, not a later chunk whose metrics were written before the
            # run stopped (its state was never checkpointed: a resume trains it again)
            metrics = rd.chunk_metrics(done)
        except CheckpointError as e:
            if ended():  # the run finished while it was read, and cleared its checkpoint
                return load_run(p, env=env)
            raise RunLoadError(str(e).splitlines()[0]) from None
        model, obs_norm, source = state.model, state.obs_norm, f"checkpoint after chunk {done}"
    elif os.path.lexists(p / "summary.json"):  # finished (a finished run keeps no checkpoint), its model file gone
        raise RunLoadError(missing_model(p))
    else:
        raise RunLoadError(f"{str(p)!r} holds no trained model yet (no model.eqx, no checkpoint): the run stopped "
                           f"before its first checkpoint; continue it with `pobax train --resume {p}`.")
    if finished and sealed is _UNREAD:  # it finished while it was read as unfinished: read again, through its seal
        return load_run(p, env=env)
    if sealed is not _UNREAD and finished:
        summary = _checked_summary(sealed, rd.path / "summary.json", len(cfg.grid()))
    else:
        summary = summarize(cfg, metrics) if len(metrics) else {}
    run = LoadedRun(cfg, runs.env, model, obs_norm, metrics, summary, p, finished, source, record,
                    None if finished else done)
    _check_finite(run)
    return run


def _checked_summary(summary: Any, path: Path, sets: int) -> dict:
    """A finished run's summary (read from `path`, its seal checked), checked as far as what reads it needs (its
    best set, by AUC, one of the run's `sets`); else RunLoadError naming it."""
    best = summary.get("best_by_auc") if isinstance(summary, dict) else None
    if not (isinstance(best, int) and not isinstance(best, bool) and 0 <= best < sets):
        what = f"best_by_auc {best!r} is not one of its sets 0 … {sets - 1}" if isinstance(summary, dict) else \
            f"a JSON {type(summary).__name__}, not an object"
        raise RunLoadError(f"{str(path)!r} is not a summary pobax wrote ({what}): the file is damaged; restore it, "
                           f"or train the run again.")
    return summary


def diverged_runs(run: LoadedRun) -> np.ndarray:
    """Per run of `run.model` (its leading axis), whether its training diverged (the metric `nonfinite`)."""
    m = run.metrics
    if "nonfinite" not in m or not len(m):
        return np.zeros(run.num_runs, bool)
    bad = set(map(tuple, m.loc[m.nonfinite > 0, ["hp_index", "seed"]].drop_duplicates().to_numpy().tolist()))
    return np.array([(int(h), int(s)) in bad for h, s in zip(run.hp_index, run.seed_index)])


def _check_finite(run: LoadedRun) -> None:
    """Non-finite parameters only where training diverged (those runs are counted and left out everywhere); anywhere
    else the parameters file is damaged: RunLoadError naming it and the run."""
    leaves = [np.asarray(x) for x in jax.tree.leaves(eqx.filter(run.model, eqx.is_inexact_array))]
    nonfinite = np.zeros(run.num_runs, bool)
    for x in leaves:
        nonfinite |= ~np.isfinite(x.reshape(run.num_runs, -1)).all(axis=1)
    wrong = np.flatnonzero(nonfinite & ~diverged_runs(run))
    if wrong.size:
        i = int(wrong[0])
        raise RunLoadError(f"{run.source} of {str(run.path)!r} holds non-finite parameters for run {i} (set "
                           f"{int(run.hp_index[i])}, seed {int(run.seed_index[i])}), whose training did not diverge: "
                           f"the file is damaged; restore it, or train the run again.")


def missing_obs_norm(run: LoadedRun) -> bool:
    """Whether the runs normalised observations but the statistics were not saved with the model (runs finished
    before they were): the network cannot then be given the inputs it learned on."""
    return run.config.normalize_obs and run.obs_norm is None and obs_normalizable(run.env)
