"""`train`: the training loop (`pobax.agent.Runs`) with a run directory, checkpoints, progress and a summary."""

import dataclasses
import datetime
import errno
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from .._paths import printable, shell_word
from .._distributed import fetch, is_lead
from .._version import commit
from ..agent import Chunk, ConfigError, Runs, TrainConfig, TrainState, config_differences, validate
from ..env import spec
from ._args import as_path, check_bools, check_names, is_count
from ._bounds import check_fits, check_user_memory
from ._files import has_config
from ._given_env import given_env_mismatch, given_env_record
from ._listing import resume_hint
from ._loggers import check_available, make_loggers
from ._metrics_table import ordered_metrics
from ._interrupt import Interrupted, _CtrlC
from ._records import check_part_summary
from ._results import CheckpointError, RunDir, RunFinishedError, atomic_write_text, writable_dir
from ._seal import SEALS
from ._stats import summarize


@dataclasses.dataclass
class TrainResult:
    """What `train` returns: the final state of every run, the metrics table and the summary. `compile_s`: what
    starting cost beyond steady training (compiling both programs and running the initialisation, plus the first
    chunk's time beyond a steady chunk's), i.e. compilation, nearly all of it."""

    config: TrainConfig
    state: TrainState
    metrics: pd.DataFrame
    summary: dict
    run_dir: Path | None
    compile_s: float
    steps_per_s: float


def default_out(cfg: TrainConfig) -> Path:
    """The run directory of a run given none: runs/ENV-OBSERVABILITY-AGENT-TIMESTAMP, with -2, -3 ... after it where
    that exists (runs started within one second, e.g. a loop over seeds)."""
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    agent = cfg.memory + ("-ld" if cfg.double_critic else "")
    path = Path("runs") / f"{cfg.env}-{cfg.observability}-{agent}-{stamp}"
    name, n = path, 2
    while os.path.lexists(name):
        name, n = path.with_name(f"{path.name}-{n}"), n + 1
    return name


class _Progress:
    def __init__(self, enabled: bool, total: int):
        self.enabled, self.total = enabled, total
        self.tty = sys.stderr.isatty()

    def __call__(self, chunk, steps_done: int):
        if not self.enabled:
            return
        df = chunk.metrics
        ret = float(np.nanmean(df["return"])) if df["return"].notna().any() else float("nan")
        disc = float(np.nanmean(df["disc_return"])) if df["disc_return"].notna().any() else float("nan")
        msg = (f"[{chunk.index + 1}/{chunk.num_chunks}] {steps_done:,}/{self.total:,} steps per run | "
               f"{chunk.steps_per_s:,.0f} env steps/s | return {ret:.3f} (discounted {disc:.3f})")
        print(("\r" + msg) if self.tty else msg, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self):
        if self.enabled and self.tty:
            print(file=sys.stderr)


def check_resumable(path: str | os.PathLike) -> None:
    """A CheckpointError unless `path` is a run directory (its config.json), saying what to pass instead (the runs
    below it, or the command that continues a sweep's, gap's or benchmark's directory: `resume_hint`)."""
    if not has_config(path):
        raise CheckpointError(f"{str(path)!r} is not a run directory (no config.json): nothing to resume"
                              f"{resume_hint(path)}.")


def _open_for_resume(out, cfg: TrainConfig, write: bool = True, env=None) -> RunDir:
    run_dir = RunDir(out)
    check_resumable(run_dir.path)
    if write:
        run_dir.hold()  # before anything is read: another process may be writing it
    try:
        return _check_resumable(run_dir, cfg, write, env)
    except BaseException:
        run_dir.release()
        raise


def _check_resumable(run_dir: RunDir, cfg: TrainConfig, write: bool, env=None) -> RunDir:
    where = str(run_dir.path)
    record = run_dir.read_config()
    diff = config_differences(record.get("config", {}), cfg)
    if diff:
        raise CheckpointError(f"The run in {where!r} has another configuration (differs in: {', '.join(diff)}); resume "
                              f"it with its own configuration, or start a new run with another --out.")
    given = given_env_mismatch(record, env)
    if given:
        raise CheckpointError(f"The run in {where!r} {given}: resume it from Python with "
                              f"pobax.train(cfg, out, resume=True, env=...) and the environment it trained in.")
    if not (run_dir.path / "checkpoint.json").exists() and os.path.lexists(run_dir.path / "summary.json"):
        raise RunFinishedError(f"The run in {where!r} already finished (summary.json): nothing to resume.")
    run_dir.check_unfinished()  # a damaged or mixed checkpoint is refused here, before anything compiles
    try:
        if write:
            writable_dir(run_dir.path)
    except OSError as e:
        raise CheckpointError(f"Cannot write the run directory {where!r} ({e.strerror or e}): a resumed run must "
                              f"write its checkpoints and results there.") from None
    return run_dir


def _check_chunks(run_dir: RunDir, frames: list[pd.DataFrame], runs: Runs, state, first: int) -> None:
    """The resumed run builds on chunks 0 … first - 1 and on the checkpoint's state: every chunk holds its updates
    for every run, and the state is at the update after the last of them."""
    for c, df in enumerate(frames):
        start, n = c * runs.chunk_len, min(runs.chunk_len, runs.cfg.num_updates - c * runs.chunk_len)
        ok = "update" in df and len(df) == runs.num_runs * n and \
            sorted(set(df["update"].tolist())) == list(range(start, start + n))
        if not ok:
            raise CheckpointError(f"{str(run_dir.path / 'metrics' / f'{c:05d}.csv')!r} does not hold updates {start} "
                                  f"… {start + n - 1} of every run: the run directory is damaged; start a new run.")
    at = np.unique(np.asarray(state.update))
    if at.tolist() != [first * runs.chunk_len]:
        raise CheckpointError(f"{str(run_dir.path / 'checkpoint.json')!r} says {first} chunks are done, but its state "
                              f"is at update {at.tolist()} (not {first * runs.chunk_len}): the run directory is "
                              f"damaged; start a new run.")


OVERFLOW_WARNING = ("warning: an episode's return passed float32's largest value (3.4e38): it is logged as inf "
                    "(null in summary.json); scale the environment's rewards down (--reward-scale scales only what "
                    "the agent learns from, not the returns logged).")


def _returns_overflowed(metrics: pd.DataFrame) -> bool:
    """Whether a chunk's logged episode returns (undiscounted or discounted) are infinite: summed past float32."""
    return any(np.isinf(metrics[c].to_numpy(np.float64)).any() for c in ("return", "disc_return") if c in metrics)


def _check_arguments(cfg, out, max_chunks, loggers, **flags) -> Path | None:
    """A ConfigError in one line for `train`'s arguments of the wrong kind (from Python: the command line builds
    them), before anything is created: was an AttributeError from a dict, pathlib's TypeError from a number, a run
    saved for save="no", max_chunks True read as 1 (nan as no limit) and loggers "wandb" read as 'w', 'a', ....
    Returns `out` as a path (`~` expanded), or None."""
    if not isinstance(cfg, TrainConfig):
        raise ConfigError(f"train needs a TrainConfig, got a {type(cfg).__name__}: build one with TrainConfig(...) "
                          f"(from a dict of its fields: pobax.agent.config_from_dict(fields)).")
    path = as_path("train", "out", out, ConfigError, none=True, what="a directory path")
    check_bools("train", ConfigError, **flags)
    if max_chunks is not None and not is_count(max_chunks):
        raise ConfigError(f"--max-chunks must be a positive integer, or None (every chunk), got {max_chunks!r}.")
    check_names("train", "loggers", loggers, ConfigError)
    return path


def train(
    cfg: TrainConfig,
    out: str | Path | None = None,
    *,
    save: bool = True,
    progress: bool = True,
    resume: bool = False,
    max_chunks: int | None = None,
    devices: list | None = None,
    loggers: tuple[str, ...] = (),
    on_start: Callable[[Path], None] | None = None,
    on_chunk: Callable[[Chunk], None] | None = None,
    env=None,
) -> TrainResult:
    """Train every hyperparameter set × seed of `cfg` together. Writes a run directory unless `save=False`: `out`
    (`~` expanded), by default a new runs/ENV-OBSERVABILITY-AGENT-TIMESTAMP (`default_out`).

    The run directory gets a checkpoint of the whole training state at every chunk boundary. `resume=True` continues
    the interrupted run in `out` (which must hold the same configuration) from its last checkpoint, and produces the
    same metrics, bit for bit, as an uninterrupted run. `max_chunks` stops after that many chunks in this call,
    leaving a resumable run (the returned summary covers the chunks done so far). `loggers` ("tensorboard", "wandb")
    also send every chunk's metrics to those trackers, one logical run per (hyperparameter set, seed). `devices`
    (default: as many as the runs' environments fill, `pobax._placement`; every device of every process in a
    multi-process run) are the devices the runs are sharded over. `on_start` is called with
    the run directory once it is created or opened, before anything is compiled. `env`: the environment to train in
    instead of `cfg.env`'s registered one (e.g. that one wrapped), with its observation and action spaces (`Runs`);
    a run directory records `cfg` and the environment's classes and a digest of its parameters (`env_digest`), so
    resume such a run (or `load_run` it) from Python with the same `env`: another is refused; its listing and
    figures name it by its classes, not `cfg.env`, and show none of `cfg.env`'s reference returns. Ctrl-C raises
    `Interrupted`, which names the run directory to resume.

    `on_chunk` is called with every chunk (`pobax.agent.Chunk`: its index, metrics, seconds and training state) once
    it is recorded: its metrics written, its checkpoint saved, its progress shown. Use it to log, plot or check
    training as it goes; an exception it raises stops training there (a KeyboardInterrupt as Ctrl-C does: raised
    as `Interrupted`), and a resume continues from the last checkpoint.

    In a multi-process run (`pobax.init_distributed`) every process makes the same call; the runs are sharded over
    the devices of all of them, every process gets every run's metrics and state (and calls `on_chunk`), and process
    0 alone writes the run directory (a resume reads it in every process: put it on a file system they share).
    """
    out = _check_arguments(cfg, out, max_chunks, loggers, save=save, progress=progress, resume=resume)
    for name, hook in (("on_start", on_start), ("on_chunk", on_chunk)):  # (was a TypeError after the first chunk)
        if hook is not None and not callable(hook):
            raise ConfigError(f"train: {name} must be a function (or None), got {hook!r}.")
    validate(cfg)
    check_fits(cfg, devices)
    check_available(loggers)
    if resume and (out is None or not save):
        raise CheckpointError("resume needs the run directory to continue: pass it as `out` (--out / --resume).")
    runs = Runs(cfg, devices, env)
    check_user_memory(cfg, runs.env)
    lead = is_lead()
    run_dir = None
    if resume:
        run_dir = _open_for_resume(out, cfg, write=lead, env=env)
        if lead:
            run_dir.remove_stray_temporaries()
    elif save and lead:
        run_dir = RunDir.create(out if out is not None else default_out(cfg), {  # taken before it is written
            "config": dataclasses.asdict(cfg), "hyperparameter_sets": runs.grid,
            "env_spec": {"categories": spec(cfg.env).categories, "gamma": runs.env.gamma,
                         "reference": spec(cfg.env).reference(cfg.observability)} if env is None
            else {"categories": [], "gamma": runs.env.gamma, "reference": {}},  # cfg.env's figures are not its
            "jax": jax.__version__, "device": str(jax.devices()[0].device_kind), "pobax_commit": commit(),
            **({} if env is None else given_env_record(env)),
        })
    writer = run_dir if lead else None  # the run directory, where this process writes it
    trackers, show, timing, ctrl_c, overflow_told = [], None, [], _CtrlC(), False
    try:  # until the end: a Ctrl-C says how to resume; the trackers close; the run directory is released
        if on_start is not None and writer is not None:
            on_start(writer.path)
        trackers = make_loggers(loggers if lead else (), writer.path if writer is not None else None,
                                dataclasses.asdict(cfg))
        show = _Progress(progress and lead, cfg.num_updates * cfg.steps_per_update)
        with ctrl_c:
            t_init = time.perf_counter()
            if resume and not (run_dir.path / "checkpoint.json").exists():  # stopped before its first checkpoint
                if progress:
                    print(f"no checkpoint in {run_dir.path} yet: training from the start", file=sys.stderr, flush=True)
                state, first, frames = runs.init(), 0, []
            elif resume:
                state, first = run_dir.load_checkpoint(runs.template())
                frames = run_dir.chunks(first)
                _check_chunks(run_dir, frames, runs, state, first)
            else:
                state, first, frames = runs.init(), 0, []
            init_s = time.perf_counter() - t_init
            last = runs.num_chunks if max_chunks is None else min(runs.num_chunks, first + max_chunks)
            # This process's session, after the earlier ones' (less any chunk past the checkpoint: trained again).
            sessions = writer.sessions(before=first) if writer is not None and resume else []
            sessions.append({"started": datetime.datetime.now().isoformat(timespec="seconds"), "from_chunk": first,
                             "device": str(jax.devices()[0].device_kind), "jax": jax.__version__,
                             "pobax_commit": commit(), SEALS: True, "chunks": timing})
            for chunk in runs.chunks(state, first, last):
                state = chunk.state
                frames.append(chunk.metrics)
                timing.append({"chunk": chunk.index, "seconds": chunk.seconds, "env_steps": chunk.env_steps})
                for t in trackers:
                    t.log(chunk.metrics)
                if writer is not None:
                    writer.check_in_place()
                    writer.write_chunk(chunk.index, chunk.metrics)
                    writer.write_sessions(sessions)  # before the checkpoint that counts this chunk as done
                if save and chunk.index + 1 < runs.num_chunks:
                    host = fetch(state)  # in every process: the state may span several
                    if writer is not None:
                        writer.save_checkpoint(host, chunk.index + 1, runs.num_chunks, dataclasses.asdict(cfg))
                show(chunk, int(chunk.metrics["env_step"].max()))
                if lead and not overflow_told and _returns_overflowed(chunk.metrics):
                    overflow_told = True
                    print(OVERFLOW_WARNING, file=sys.stderr, flush=True)
                if on_chunk is not None:
                    on_chunk(chunk)
                if ctrl_c.requested and chunk.index + 1 < last:  # a Ctrl-C whose KeyboardInterrupt was dropped
                    raise KeyboardInterrupt

        state = fetch(state)
        metrics = ordered_metrics(frames)
        seconds = [t["seconds"] for t in timing]
        # compile_s: this process's start-up; steps/s and wall time: every session's chunks (a session's first chunk
        # holds its compile and is left out of the steps/s)
        steady = [c["env_steps"] / c["seconds"] for s in sessions for c in s["chunks"][1:]]
        compile_s = init_s + max(0.0, seconds[0] - float(np.median(seconds[1:]))) if len(seconds) > 1 else float("nan")
        steps_per_s = float(np.median(steady)) if steady else float("nan")
        summary = summarize(cfg, metrics, tuple(n for names in runs.env.episode_metrics.values() for n in names))
        finished = last == runs.num_chunks
        summary.update(compile_s=compile_s, steps_per_s=steps_per_s,
                       wall_s=float(sum(c["seconds"] for s in sessions for c in s["chunks"])), finished=finished,
                       sessions=[{k: v for k, v in s.items() if k != "chunks"} | {"chunks": len(s["chunks"])}
                                 for s in sessions])
        if writer is not None and finished:
            writer.check_in_place()
            # the last checkpoint goes last: until then, a resume trains the last chunk again and rewrites these
            writer.write_metrics(metrics)
            rows = [dict(c, session=i) for i, s in enumerate(sessions) for c in s["chunks"]]
            atomic_write_text(writer.path / "timing.csv", pd.DataFrame(rows).to_csv(index=False))
            writer.save_model(state.model, state.obs_norm)
            writer.write_summary(summary)
            writer.clear_checkpoint()  # the run is complete: its results are the files above
        return TrainResult(cfg, state, metrics, summary, run_dir.path if run_dir else None, compile_s, steps_per_s)
    except KeyboardInterrupt:
        where = run_dir.path if run_dir is not None else None
        raise Interrupted(where, where is not None and (where / "checkpoint.json").exists(), ctrl_c.signum) from None
    except OSError as e:  # e.g. the disk filled up: what was written whole stays, and says how to go on
        if run_dir is None or e.errno is None:
            raise
        again = f"pobax train --resume {shell_word(run_dir.path)}"
        fix = "make room" if e.errno in (errno.ENOSPC, errno.EDQUOT) else "fix that"
        hint = (f"the last checkpoint is in {printable(run_dir.path)}: {fix}, then continue with {again}"
                if (run_dir.path / "checkpoint.json").exists() else
                f"no checkpoint was written yet: {fix}, then start it again with {again}")
        error = OSError(e.errno, f"{e.strerror} ({printable(e.filename)}); {hint}")
        error.advised = True  # (the command line adds no advice of its own)
        raise error from e
    except BaseException:
        if run_dir is not None and not resume and not timing:  # failed before its first chunk: leave nothing
            in_place = run_dir.in_place()  # (not where the directory at its path is another now)
            run_dir.release()
            if in_place:
                run_dir.discard()
        raise
    finally:
        for t in ([show] if show is not None else []) + trackers:
            t.close()
        if run_dir is not None:
            run_dir.release()


class ConfigMismatchError(ValueError):
    """An output directory holds a run of another configuration (gap, benchmark, sweep)."""


def check_same_config(path: Path, cfg, what: str = "a run", advice: str = "pass another --out") -> None:
    """Refuse (`ConfigMismatchError`) the run directory `path` if its config.json holds another configuration than
    `cfg`; `what` names the run in the message, `advice` says what to do."""
    diff = config_differences(RunDir(path).read_config().get("config", {}), cfg)
    if diff:
        raise ConfigMismatchError(f"{str(path)!r} holds {what} with another configuration (differs in: "
                                  f"{', '.join(diff)}); {advice}.")


def train_or_reuse(cfg, path: Path, progress: bool, devices: list | None = None,
                   on_chunk: Callable[[Chunk], None] | None = None):
    """Train one agent into `path`, or pick up what a previous (interrupted) call left there: a finished run is
    reused, an interrupted one resumed (or reused, when another process finishes it first), anything else is kept aside
    under a new name (unless another process holds it: RunDirBusyError). Returns
    (metrics, summary, run directory). `devices`, `on_chunk`: as `train`'s."""
    if (path / "config.json").exists():
        check_same_config(path, cfg)
        if not (path / "summary.json").exists():
            if progress:
                print(f"   resuming the interrupted run in {path}", flush=True)
            try:
                r = train(cfg, path, progress=progress, resume=True, devices=devices, on_chunk=on_chunk)
                return r.metrics, r.summary, r.run_dir
            except RunFinishedError:  # another process (a benchmark into the same --out) finished it meanwhile
                pass
        if progress:
            print(f"   reusing the finished run in {path}", flush=True)
        rd = RunDir(path)
        summary = rd.read_summary()
        check_part_summary(summary, path / "summary.json", kind="a run's summary",
                           fix="restore it, or move the run directory aside to train it again")
        return rd.metrics(), summary, path
    if path.exists() and any(path.iterdir()):
        held = RunDir(path)
        held.hold()  # RunDirBusyError while another process creates it (its config.json not yet written)
        held.release()
        if (path / "config.json").exists():  # another process created it meanwhile
            return train_or_reuse(cfg, path, progress, devices, on_chunk)
        aside = path.with_name(f"{path.name}.incomplete-{datetime.datetime.now():%Y%m%d-%H%M%S}")
        path.rename(aside)
        if progress:
            print(f"   kept an unusable earlier run aside as {aside}", flush=True)
    r = train(cfg, path, progress=progress, devices=devices, on_chunk=on_chunk)
    return r.metrics, r.summary, r.run_dir
