"""Reading a command's flags: which training flags were given (as tyro reads them), the training configuration and
the overrides they make, the devices and the multi-process run they name; `UsageError`, a command line that cannot
run."""

import argparse
import dataclasses
import sys
import typing
from pathlib import Path
from typing import Literal

import tyro

from ..agent import TrainConfig
from ..agent._network import unread_by_all
from .commands import Sweep, Train

_TRAIN_FIELDS = {f.name for f in dataclasses.fields(TrainConfig)}


class UsageError(ValueError):
    """A command line that cannot run: printed as one line, exit 2."""


class ScriptParser(argparse.ArgumentParser):
    """argparse for the scripts under `benchmarks/`: a command line it cannot read is one line on stderr (what is
    wrong, and where the usage is), exit 2, as pobax's own commands; `--help` prints the usage as usual."""

    def error(self, message: str) -> typing.NoReturn:
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _shifted(value, hint):
    """A value of the field type `hint` that differs from `value` (`_given_fields`)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is Literal:
        return next(a for a in args if a != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, tuple) and typing.get_args(hint)[:1] == (str,):  # tuple[str, ...]
        return (*value, "~")
    if isinstance(value, tuple):
        return tuple(v + 1 for v in value) or (1.0,)
    if isinstance(value, str):
        return value + "~"
    return 1  # None, in an `int | None` field


def _given_fields(cmd, argv: list[str]) -> frozenset[str]:
    """The TrainConfig fields given on the command line, as tyro reads it: the same arguments parsed again over
    defaults that all differ from the real ones. A field given has the same value in both parses; one left to its
    default differs. (A field given with its default value counts as given: it overrides a preset.)"""
    cls = type(cmd)
    hints = typing.get_type_hints(cls)
    shifted = {f.name: _shifted(f.default, hints[f.name]) if f.default is not dataclasses.MISSING else
               _shifted(f.default_factory(), hints[f.name]) for f in dataclasses.fields(cls) if f.name in _TRAIN_FIELDS}
    again = tyro.cli(cls, args=argv, default=dataclasses.replace(cls(), **shifted))
    return frozenset(k for k in _TRAIN_FIELDS if getattr(again, k) == getattr(cmd, k))


def _overrides(cmd, given: frozenset[str], per_agent: tuple[str, ...] = ()) -> dict:
    """The training flags given explicitly, as overrides of every agent's preset; `per_agent` fields are refused."""
    explicit = given
    refused = sorted(explicit & set(per_agent))
    if refused:
        raise UsageError(f"--{refused[0].replace('_', '-')} is set per agent by this command; choose agents with "
                         f"--agents (and --memories) instead.")
    return {k: getattr(cmd, k) for k in explicit}


def _train_config(cmd: Train, given: frozenset[str]) -> TrainConfig:
    from pobax.agent import apply_preset, resolve_preset

    cfg = TrainConfig(**{name: getattr(cmd, name) for name in _TRAIN_FIELDS})
    if cmd.preset not in (None, "paper", "paper-original") and Path(cmd.preset).is_dir():
        raise UsageError(f"--preset {cmd.preset!r} is a directory; pass a preset file (e.g. best.json, which sweep "
                         f"writes), paper or paper-original.")
    if cmd.preset is not None:
        cfg = apply_preset(cfg, resolve_preset(cmd.preset, cfg), keep=set(given))
    return cfg


def _check_read(cfg: TrainConfig, given: frozenset[str], axes: dict | None = None) -> None:
    """Refuse a training flag (or `--axis` key) that no agent of the command reads: `--ld-weight` without
    `--double-critic`, `--num-heads` with a GRU. An axis over `memory`, `double_critic`, `gating` or
    `action_concat` counts each agent."""
    axes = axes or {}
    variants = [cfg]
    for key in ("memory", "double_critic", "gating", "action_concat"):
        variants = [dataclasses.replace(v, **{key: x}) for v in variants for x in axes.get(key, [getattr(v, key)])]
    unread = unread_by_all(variants, sorted(set(given) | set(axes)))
    if unread:
        f, (who, flag) = next(iter(unread.items()))
        flag_f = f"--{f.replace('_', '-')}" + (f"/--no-{f.replace('_', '-')}" if type(getattr(cfg, f)) is bool else "")
        name = f"--axis {f}" if f in axes and f not in given else flag_f
        trained = ", ".join(dict.fromkeys(
            v.memory + (" with two critics" if v.double_critic else " with one critic")
            + (" without gates" if v.memory == "trxl" and not v.gating else "")
            + (" without the previous action" if flag == "--action-concat" and not v.action_concat else "")
            for v in variants))
        raise UsageError(f"{name} is read only by {who} ({flag}) and this command trains {trained}, so it would "
                         f"change nothing: add {flag} or drop {name}.")


def _devices(indices: tuple[int, ...]) -> list | None:
    """The devices of `--devices` (None: every device)."""
    if not indices:
        return None
    import jax

    devs = jax.devices()
    bad = [i for i in indices if not 0 <= i < len(devs)]
    if bad:
        raise UsageError(f"--devices {bad[0]}: the device indices are 0 .. {len(devs) - 1} "
                         f"({', '.join(str(d) for d in devs)}).")
    if len(set(indices)) < len(indices):
        raise UsageError("--devices names a device twice.")
    return [devs[i] for i in indices]


def _distributed(cmd) -> None:
    """Join a multi-process run if the command line asks for one (before anything else uses JAX)."""
    if not isinstance(cmd, Train) or not (cmd.distributed or cmd.coordinator is not None
                                          or cmd.num_processes is not None or cmd.process_id is not None):
        return
    if isinstance(cmd, Sweep):
        raise UsageError("sweep runs in one process (over every local device); a multi-process run is `pobax "
                         "train`'s: train the grid with it, then select with `pobax results`.")
    from pobax import init_distributed

    if cmd.distributed and cmd.num_processes is not None:
        raise UsageError("--distributed reads the processes from the cluster; drop --num-processes/--process-id.")
    try:
        init_distributed(cmd.coordinator, cmd.num_processes, cmd.process_id)
    except RuntimeError as e:
        raise UsageError(f"cannot join the multi-process run: {str(e).splitlines()[0] if str(e) else e}") from None
