"""Sweeps: a grid of hyperparameters, selection by area under the curve, a preset file of the winner.

- Numeric hyperparameters (lr, λ0, λ1, β, ...) × seeds are vmapped in one compiled program (`train`);
  structural axes (hidden size, num_envs, memory, ...) are separate programs compiled one after another.
- A program whose runs would not fit in device memory is split along its longest numeric axis into parts
  trained one after another; the number of runs per program comes from `runs_per_program` (an estimate of
  one run's bytes against the device's memory), or is given.
- Selection: the set with the largest mean (over seeds) area under the discounted learning curve (`auc`: the
  mean of the per-update average discounted episode return over all updates, i.e. the area under the curve
  of return against env steps divided by the steps), the paper's criterion. It is written to `best.json`,
  a preset that `train --preset` loads, and optionally re-run with fresh seeds (the paper uses 30).
- Resumable: the same sweep into the same `out` reuses finished programs and resumes an interrupted one from its
  last checkpoint; a sweep with another grid, axes, environment or memory is refused there. A program too large
  for one device is split by the device's memory: on a machine with other devices, pass the split (`max_runs`).
"""

import dataclasses
import datetime
import itertools
import json
import math
import os
from collections.abc import Callable
from pathlib import Path

import jax

from .._distributed import single_process
from ..agent import NUMERIC, Chunk, TrainConfig, config_from_dict, init_state, make_env, rollout, structural, validate
from ..agent._config import INT32_MAX, ConfigError, config_values
from ..agent._presets import load_preset
from ._args import check_bools, is_int
from ._bounds import check_fits, check_user_memory
from ._files import OUT_MARKERS, claim_out, read_json, write_json
from ._run import check_same_config, train_or_reuse


def write_preset(path: str | Path, cfg: TrainConfig, hyperparameters: dict, **provenance) -> None:
    """A preset file (`train --preset FILE`): cfg's structural settings with one hyperparameter set, plus where it
    came from."""
    if not isinstance(cfg, TrainConfig):
        raise TypeError(f"write_preset: cfg must be a TrainConfig, got {type(cfg).__name__}.")
    if not isinstance(hyperparameters, dict) or set(hyperparameters) - set(NUMERIC):
        extra = sorted(set(hyperparameters) - set(NUMERIC)) if isinstance(hyperparameters, dict) else None
        raise ConfigError(f"write_preset: hyperparameters must be a dict of {', '.join(NUMERIC)}"
                          + (f"; not one: {', '.join(map(str, extra))}" if extra else "") + ".")
    values = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in NUMERIC and k not in ("seed", "num_seeds")}
    values.update({k: [hyperparameters[k]] for k in NUMERIC if k in hyperparameters})
    config_values(values, source="write_preset's preset", strict=True)  # (what load_preset refuses: not written)
    path = Path(path)
    _check_preset_path(path)
    write_json(path, {"preset": values, **provenance})


def _check_preset_path(path: Path) -> None:
    """FileExistsError where `path` holds something other than a preset (an earlier sweep's best.json): a preset
    written there would replace it."""
    if os.path.lexists(path):
        try:
            data = read_json(path)
            ours = isinstance(data, dict) and "preset" in data and load_preset(path) is not None  # (its values read)
        except (ValueError, OSError):  # (ConfigError, CheckpointError: not JSON, not a preset, not a file)
            ours = False
        if not ours:
            raise FileExistsError(f"{str(path)!r} exists and is not a preset file pobax wrote: name another file, or "
                                  f"move it aside.")


def _nbytes(tree) -> int:
    total = 0
    for x in jax.tree.leaves(tree):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            total += 8 * math.prod(x.shape)
        else:
            total += x.dtype.itemsize * math.prod(x.shape)
    return total


def estimate_run_bytes(cfg) -> int:
    """Device bytes of one run: its training state plus four times one rollout's trajectory (the trajectory,
    GAE's arrays, and a minibatch's activations and gradients are of that order)."""
    env = make_env(cfg)
    scfg = structural(cfg)
    state = jax.eval_shape(lambda k: init_state(scfg, env, k), jax.random.key(0))
    traj = jax.eval_shape(lambda s: rollout(scfg, env, s)[1], state)
    return _nbytes(state) + 4 * _nbytes(traj)


def runs_per_program(cfg, memory_fraction: float = 0.5) -> int | None:
    """How many runs fit in one program: `memory_fraction` of the first device's memory over the estimate of
    one run. None where the device does not report its memory (CPU): no limit."""
    stats = jax.devices()[0].memory_stats() or {}
    limit = stats.get("bytes_limit")
    if not limit:
        return None
    return max(1, int(memory_fraction * limit // estimate_run_bytes(cfg)))


def _parts(cfg, max_runs: int | None) -> list:
    """cfg split along its longest numeric axis so that each part has at most `max_runs` runs (if possible)."""
    runs = len(cfg.grid()) * cfg.num_seeds
    if max_runs is None or runs <= max_runs:
        return [cfg]
    axis = max(NUMERIC, key=lambda k: len(getattr(cfg, k)))
    values = getattr(cfg, axis)
    per_value = runs // len(values)
    step = max(1, max_runs // per_value)
    return [dataclasses.replace(cfg, **{axis: values[i : i + step]}) for i in range(0, len(values), step)]


#: Seeds of a re-run start this far from the selection's: selection and evaluation must not share seeds.
RERUN_SEED_OFFSET = 10_000


def rerun_config(cfg, hyperparameters: dict, num_seeds: int | None = None):
    """`cfg` with one selected hyperparameter set and fresh seeds, for re-running what a sweep selected (the base seed
    `RERUN_SEED_OFFSET` on, modulo 2**32: a seed is 32 bits)."""
    return dataclasses.replace(cfg, seed=(cfg.seed + RERUN_SEED_OFFSET) % 2**32,
                               num_seeds=cfg.num_seeds if num_seeds is None else num_seeds,
                               **{k: (v,) for k, v in hyperparameters.items()})


#: Structural axes a sweep refuses: selection by AUC across them would not select a setting of the agent.
UNSELECTABLE_AXES = {
    "env": "returns of different environments are not comparable: sweep each environment (or `pobax benchmark "
           "--envs ...`)",
    "observability": "another observability is another problem, not a setting of the agent: sweep each (or "
                     "`pobax gap` for floor and ceiling)",
    "seed": "selecting among seeds selects luck: --num-seeds trains more seeds of every set",
}


def _check_axes(axes: dict) -> None:
    """Refuse axes a sweep cannot select among (`UNSELECTABLE_AXES`), and an axis without values or with a value
    twice (its program would train twice)."""
    if not isinstance(axes, dict):
        raise ValueError(f"sweep: axes must be a dict of TrainConfig fields to lists of values (e.g. "
                         f"axes={{'hidden_size': [64, 128]}}), got a {type(axes).__name__}.")
    unknown = sorted(str(k) for k in axes if k not in {f.name for f in dataclasses.fields(TrainConfig)})
    if unknown:
        raise ValueError(f"--axis {unknown[0]}: not a TrainConfig field; `pobax train --help` lists them.")
    for key, values in axes.items():
        if key in UNSELECTABLE_AXES:
            raise ValueError(f"--axis {key}: {UNSELECTABLE_AXES[key]}.")
        if not isinstance(values, list | tuple) or not values:
            raise ValueError(f"--axis {key} needs a list of values (e.g. axes={{'hidden_size': [64, 128]}}), got "
                             f"{values!r}.")
        twice = [v for i, v in enumerate(values) if v in values[:i]]
        if twice:
            raise ValueError(f"--axis {key} gives {twice[0]!r} more than once: give each value once.")


def sweep(cfg, out=None, *, axes: dict | None = None, rerun_seeds: int = 0, progress: bool = True,
          max_runs: int | None = None, devices: list | None = None,
          on_chunk: Callable[[Chunk], None] | None = None) -> dict:
    """Train `cfg`'s grid for every combination of the structural `axes`, select by AUC (`select_best`), write
    `best.json`.

    Returns a report (also written as `sweep.json`): every program's run directory and summary, the selected
    set, the preset's path and, with `rerun_seeds`, the re-run's final discounted return (mean, 95% CI). `devices`,
    `on_chunk` (called with every chunk of every program trained): as `train`'s. Called again with the same
    settings and `out`, it continues what an earlier call left there.
    """
    single_process("sweep")
    if not isinstance(cfg, TrainConfig):
        raise TypeError(f"sweep needs a TrainConfig, got a {type(cfg).__name__}: build one with TrainConfig(...) (from a "
                        f"dict of its fields: pobax.agent.config_from_dict(fields)).")
    axes = {} if axes is None else axes
    out = Path(out) if out is not None else Path("runs") / f"sweep-{cfg.env}-{cfg.memory}-{datetime.datetime.now():%Y%m%d-%H%M%S}"
    for flag, value in (("--rerun-seeds", rerun_seeds), ("--max-runs", max_runs)):
        if not (value is None and flag == "--max-runs") and not is_int(value):
            raise ValueError(f"{flag} takes a whole number, got {value!r}.")
    check_bools("sweep", progress=progress)
    if not 0 <= rerun_seeds <= INT32_MAX:
        raise ValueError(f"--rerun-seeds must be 0 (no re-run) or a positive integer of at most {INT32_MAX:,}, got "
                         f"{rerun_seeds:,}.")
    if max_runs is not None and max_runs < 1:
        raise ValueError(f"--max-runs must be a positive integer (runs per program), got {max_runs:,}.")
    _check_axes(axes)
    for combo in itertools.product(*axes.values()):  # every program is checked before anything is written
        validate(pcfg := dataclasses.replace(cfg, **dict(zip(axes, combo))))
        check_user_memory(pcfg, make_env(pcfg))  # its environment builds, a cell of the user's returns what it must
        for part in _parts(pcfg, max_runs if max_runs is not None else runs_per_program(pcfg)):
            check_fits(part, devices)  # as `train` checks it, before the first program trains
        if rerun_seeds:  # the re-run too (its set is one of the grid's: the first stands for them all)
            try:
                rcfg = rerun_config(pcfg, {k: getattr(cfg, k)[0] for k in NUMERIC}, rerun_seeds)
                validate(rcfg)
                check_fits(rcfg, devices)
            except ValueError as e:
                raise type(e)(f"--rerun-seeds {rerun_seeds:,}: {e}") from None
    # the same sweep again (after an interruption, or on another machine) picks up where it stopped; others are refused
    grid = {k: getattr(cfg, k) for k in NUMERIC}
    owner = {"command": "sweep", "env": cfg.env, "memory": cfg.memory, "axes": axes, "grid": grid}
    owner = json.loads(json.dumps(owner))  # as the marker file reads back (tuples as lists)
    held = claim_out(out, OUT_MARKERS["sweep"], owner)
    # the axes in the order the sweep's marker holds them: the same axes given in another order continue it (its
    # programs are named in that order), not train every program again under other names
    axes = {k: axes[k] for k in held["axes"]}
    # what the end writes, checked before anything trains: a best.json that is not a preset, a sweep.json that is
    # not a file, would only be refused after every program had trained
    _check_preset_path(out / "best.json")
    if os.path.lexists(out / "sweep.json") and not (out / "sweep.json").is_file():
        raise FileExistsError(f"{str(out / 'sweep.json')!r} exists and is not a file: move it aside.")
    plan = []  # per program: its axis values, name and (run directory, configuration) of each part
    for combo in itertools.product(*axes.values()):  # split and re-run as an earlier call left them, or refused
        values = dict(zip(axes, combo))
        pcfg = dataclasses.replace(cfg, **values)
        name = "-".join(f"{k}={v}" for k, v in values.items()) or "base"
        split = _parts(pcfg, max_runs if max_runs is not None else runs_per_program(pcfg))
        _check_layout(out, name, split)
        dirs = [out / name] if len(split) == 1 else [out / name / f"part-{i}" for i in range(len(split))]
        for run_dir, part in zip(dirs, split):  # a program trained with other flags: refused before any other trains
            if (run_dir / "config.json").exists():  # (as `train_or_reuse` looks)
                check_same_config(run_dir, part)
        plan.append((values, name, list(zip(dirs, split))))
    _check_rerun(out, rerun_seeds)
    programs, parts = [], []
    for values, name, split in plan:
        for i, (run_dir, part) in enumerate(split):
            if progress:
                print(f"== {name}{'' if len(split) == 1 else f' part {i + 1}/{len(split)}'}: "
                      f"{len(part.grid())} sets × {part.num_seeds} seeds", flush=True)
            _, summary, run_dir = train_or_reuse(part, run_dir, progress, devices, on_chunk)
            programs.append({"axis": values, "run_dir": str(run_dir), "summary": summary})
            parts.append(part)
    best, part = select_best(programs, parts, out)
    hyper = best["hyperparameters"]
    preset = out / "best.json"
    write_preset(preset, part, hyper, selected_by="largest mean AUC of the discounted return over seeds",
                 selected_from=str(out), auc=best["disc_return_auc"], final_disc_return=best["disc_return"])
    report = {"out": str(out), "programs": programs, "best": best, "preset": str(preset)}
    if rerun_seeds:
        rcfg = rerun_config(part, hyper, rerun_seeds)
        if progress:
            print(f"== re-run of the selected set with {rerun_seeds} fresh seeds", flush=True)
        _, summary, run_dir = train_or_reuse(rcfg, out / "rerun", progress, devices, on_chunk)
        d = summary["sets"][0]["disc_return"]
        report["rerun"] = {"run_dir": str(run_dir), "mean": d["mean"], "ci_low": d["ci_low"], "ci_high": d["ci_high"]}
    write_json(out / "sweep.json", report)
    return report


def _runs(path: Path) -> int | None:
    """The runs (sets × seeds) of the run directory `path` as its config.json says; None where it does not read."""
    try:
        cfg = config_from_dict(read_json(path / "config.json")["config"])
        return len(cfg.grid()) * cfg.num_seeds
    except (ValueError, OSError, KeyError, TypeError):
        return None


def _check_layout(out: Path, name: str, split: list) -> None:
    """Refuse, before anything trains, a split of program `name` into parts (`max_runs`, or the device's memory)
    other than the one an earlier call trained in `out`: continued, the finished program would be moved aside as
    incomplete and trained again in the new parts."""
    where = out / name
    parts = sorted(p for p in where.glob("part-*") if p.name[5:].isdigit()) if where.is_dir() else []
    if os.path.lexists(where / "config.json") and len(split) > 1:
        runs = _runs(where)
        raise ValueError(f"{str(where)!r} holds program {name} trained as one program; this call splits it in "
                         f"{len(split)} parts (--max-runs, or this device's memory): pass --max-runs "
                         f"{runs if runs else 'as before'} to continue it, or another --out.")
    if parts and (len(parts) != len(split) or _runs(parts[0]) != len(split[0].grid()) * split[0].num_seeds):
        runs = _runs(parts[0])
        raise ValueError(f"{str(where)!r} holds program {name} trained in {len(parts)} parts"
                         + (f" of up to {runs} run{'s' * (runs != 1)}" if runs else "") + f"; this call splits it in {len(split)}: pass "
                         f"--max-runs {runs if runs else 'as before'} to continue it, or another --out.")


def _check_rerun(out: Path, rerun_seeds: int) -> None:
    """Refuse, before anything trains, a re-run of another number of seeds than the one in `out/rerun`."""
    path = out / "rerun"
    if rerun_seeds and os.path.lexists(path / "config.json"):
        try:
            held = config_from_dict(read_json(path / "config.json")["config"]).num_seeds
        except (ValueError, OSError, KeyError, TypeError):
            return  # (a damaged re-run: train_or_reuse names it)
        if held != rerun_seeds:
            raise ValueError(f"--rerun-seeds {rerun_seeds:,}: {str(path)!r} holds the selected set's re-run with "
                             f"{held:,} seed{'s' * (held != 1)}: pass --rerun-seeds {held:,} to continue it, or another --out.")


def select_best(programs: list[dict], configs: list[TrainConfig], out) -> tuple[dict, TrainConfig]:
    """The set a sweep selects among the sets of all its programs: the largest mean AUC of the discounted return
    over seeds, among the sets with no diverged run unless every set has one (as `summarize` selects within a
    program). `programs`: the report's entries ({"axis": the structural values, "run_dir", "summary"}), `configs`:
    the configuration each one trained; `out` names the sweep in errors. Returns (the report's "best" entry, the
    configuration of the selected set's program). A ValueError where nothing can be selected: every run diverged,
    or no set finished an episode."""
    candidates = [(s["disc_return_auc"]["mean"], p["axis"], c, s, p["run_dir"])
                  for p, c in zip(programs, configs) for s in p["summary"]["sets"]]
    valid = [c for c in candidates if c[0] == c[0]]  # drop NaN (no finished episode)
    if not valid and candidates and all(c[3].get("diverged", 0) >= c[3].get("num_seeds", c[2].num_seeds)
                                        for c in candidates):
        raise ValueError(f"Every run of the sweep in {out} diverged (a non-finite loss or gradient): nothing to "
                         f"select; sweep smaller step sizes (--lr) or a tighter --max-grad-norm.")
    if not valid:
        raise ValueError(f"No hyperparameter set of the sweep in {out} finished an episode: nothing to select; raise "
                         f"--total-steps.")
    clean = [c for c in valid if not c[3].get("diverged")]  # as `summarize` selects
    _, values, part, s, run_dir = max(clean or valid, key=lambda c: c[0])
    best = {"axis": values, "hp_index": s["hp_index"], "hyperparameters": {k: s[k] for k in NUMERIC},
            "run_dir": run_dir, "disc_return_auc": s["disc_return_auc"], "disc_return": s["disc_return"],
            "diverged": s.get("diverged", 0), "num_seeds": s.get("num_seeds", part.num_seeds)}
    return best, part
