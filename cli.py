"""pobax command line: `python cli.py <command> --help` (also installed as `pobax`).

Commands:
  train      train PPO agents (every combination of list-valued hyperparameters × seeds in one compiled program)
  sweep      sweep a grid, select the best set by AUC, write it as a preset file (and re-run it with fresh seeds)
  gap        memory-improvability gap report: floor, GRU, λ-discrepancy, Transformer-XL and ceiling on one environment
  benchmark  the gap report's agents on a suite of environments at a named budget: one results table and figure
  results    list the runs under a directory
  plot       learning curves with 95% CIs from any set of run directories
  eval       play fresh episodes with the trained agents of a run directory: returns with 95% CIs, lengths, metrics
  render     watch one episode of a trained agent (GIF + PNG strip, with its memory), or random actions (--env)
  envs       list the registered environments

Training options (`--lr`, `--hidden-size`, ...) are `pobax.agent.TrainConfig`'s fields for every command that trains.
"""

import contextlib
import dataclasses
import errno
import io
import os
import signal
import sys
import threading
import types
import typing
from pathlib import Path

# A Ctrl-C while the imports below load JAX (about a second) is noted and honoured once they are done: a
# KeyboardInterrupt in the middle of an import would print a traceback, or be dropped by a callback.
_CTRL_C: list = []
_HOOKED = threading.current_thread() is threading.main_thread() and \
    signal.getsignal(signal.SIGINT) is signal.default_int_handler
if _HOOKED:
    signal.signal(signal.SIGINT, lambda *_: _CTRL_C.append(True))

import tyro  # noqa: E402

from pobax._cli.args import _distributed, _given_fields  # noqa: E402
from pobax._paths import shell_word  # noqa: E402
from pobax._cli.commands import COMMANDS, Benchmark, Envs, Eval, Gap, Plot, Render, Results, Sweep, Train  # noqa: E402
from pobax._cli.inspection import run_envs, run_eval, run_plot, run_render, run_results  # noqa: E402
from pobax._cli.training import run_benchmark, run_gap, run_sweep, run_train  # noqa: E402

if _HOOKED:
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if _CTRL_C:
        print("error: interrupted", file=sys.stderr)
        raise SystemExit(130)


def _one_line(box: str, argv: list[str]) -> str:
    """tyro's error box (a title, a message, then the argument's help text, a guess and where the full help is) as
    one line: the message, and the command whose --help says more."""
    sections, lines = [], []
    for raw in box.splitlines():
        line = raw.strip().strip("│").strip()
        if line.startswith(("╭", "╰")) or not line:
            continue
        if set(line) <= set("─"):
            sections.append(lines)
            lines = []
        else:
            lines.append(line)
    sections.append(lines)
    kept = [" ".join(sec) for sec in sections
            if sec and not sec[0].startswith(("Argument helptext", "For full ", "Perhaps you meant"))]
    if not kept:
        return " ".join(box.split()) or "cannot read the command line"
    command = argv[0] if argv and argv[0] in COMMANDS else None
    return "; ".join(kept) + f" (see pobax {command + ' ' if command else ''}--help)"


def _again(argv: list[str]) -> str:
    """The command line `argv` as one to type again ("" where it names no --out, which would continue nothing)."""
    if not any(a == "--out" or a.startswith("--out=") for a in argv):
        return ""
    return ": " + " ".join(["pobax", *(shell_word(a) for a in argv)])


def _interrupted(cmd, e: BaseException, argv: list[str] = ()) -> None:
    """Ctrl-C (SIGINT), or a `kill` (SIGTERM) while training, as a command ran: how to continue (`benchmark --jobs`'s
    side-by-side jobs end in a plain KeyboardInterrupt or, killed, in `Terminated`; a trainer's in `Interrupted`,
    which names its run directory)."""
    from pobax.eval import Interrupted

    code = 128 + getattr(e, "signum", signal.SIGINT)  # 130 for Ctrl-C, 143 for a `kill`, as the shell reports them
    if type(cmd) in (Gap, Benchmark):
        _error("interrupted; the same command with the same --out continues (finished agents are kept, the "
               f"interrupted one resumes from its last checkpoint){_again(argv)}", code)
    if type(cmd) is Sweep:
        _error("interrupted; the same sweep command with the same --out continues (finished programs are kept, "
               f"the interrupted one resumes from its last checkpoint){_again(argv)}", code)
    if not isinstance(e, Interrupted):
        _error("interrupted", 130)
    resume = f"pobax train --resume {shell_word(e.run_dir)}" if e.run_dir is not None else ""
    where = "" if not resume else (f"; the last checkpoint is in {e.run_dir}: continue with {resume}" if e.checkpoint
                                   else f" before the first checkpoint of {e.run_dir}: start it again with {resume}")
    killed = e.signum == signal.SIGTERM  # a `kill`: a scheduler's preemption, as the shell reports it (143)
    _error(f"{'terminated (SIGTERM)' if killed else 'interrupted'}{where}", code)


#: What to do about a file-system error a command meets, by its errno (the system's message says what is wrong).
_OS_ADVICE = {
    errno.ENAMETOOLONG: "pass a shorter path (names of at most 255 bytes)",
    errno.ENOSPC: "free disk space and run the command again (files already written are kept)",
    errno.EDQUOT: "free disk space and run the command again (files already written are kept)",
    errno.EACCES: "check the path's permissions, or pass another path",
    errno.EPERM: "check the path's permissions, or pass another path",
    errno.EROFS: "pass a path on a writable file system",
    errno.ELOOP: "a symbolic link on the path leads back to itself: fix it, or pass another path",
    errno.EISDIR: "a directory stands where pobax writes a file: move it aside, or pass another path",
    errno.ENOTDIR: "a file stands where pobax keeps a directory (the path or a folder on it): move it aside, or pass "
                   "another path",
    errno.EEXIST: "a file or link stands where pobax makes a directory: move it aside, or pass another path",
    errno.ENOENT: "a folder on the path was removed, or a link on it leads to nothing: fix it, or pass another path",
}


def _os_error_line(e: OSError) -> str:
    line = str(e).splitlines()[0] if str(e) else type(e).__name__
    advice = None if getattr(e, "advised", False) else _OS_ADVICE.get(e.errno)  # (train's says how to resume)
    return f"{line}; {advice}" if advice else line


def _empty_argument(argv: list[str]) -> str | None:
    """The option (or "an argument") given as an empty string: a path or a name left unset in a script (`--out
    "$DIR"`) would read as the current directory, or as nothing given. `--backend ""` is the backend's default."""
    for i, a in enumerate(argv):
        if not isinstance(a, str):
            continue
        flag = a[:-1] if a.startswith("--") and a.endswith("=") else None
        if a == "":
            flag = argv[i - 1] if i and argv[i - 1].startswith("--") else "an argument"
        if flag is not None and flag != "--backend":
            return flag
    return None


def _takes_several(hint) -> bool:
    """Whether a command's field of type `hint` takes several values (a tuple, possibly in a union or annotated)."""
    origin = typing.get_origin(hint)
    if origin is tuple:
        return True
    if origin is typing.Annotated:
        return _takes_several(typing.get_args(hint)[0])
    return origin in (typing.Union, types.UnionType) and any(_takes_several(a) for a in typing.get_args(hint))


def _repeated_list_flag(argv: list[str]) -> tuple[str, int] | None:
    """The first flag of several values (a tuple field of the command's dataclass) given more than once, and how many
    times: the last would replace the first's values without a word, where a user may mean them added (`--axis
    hidden_size=8 --axis num_envs=4` swept num_envs alone)."""
    command = COMMANDS.get(argv[0]) if argv and isinstance(argv[0], str) else None
    if command is None:
        return None
    hints = typing.get_type_hints(command, include_extras=True)
    for field in dataclasses.fields(command):
        if not _takes_several(hints[field.name]):
            continue
        flag = "--" + field.name.replace("_", "-")
        n = sum(1 for a in argv if isinstance(a, str) and (a == flag or a.startswith(flag + "=")))
        if n > 1:
            return flag, n
    return None


def _error(msg: str, code: int = 2) -> None:
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(code)


def _printable_streams() -> None:
    """Let stdout and stderr print any path: a name that is not UTF-8 (argv and the file system hand it over with
    its bytes as surrogates) raised UnicodeEncodeError on a strict UTF-8 stream (a UTF-8 locale other than C.UTF-8,
    PYTHONIOENCODING=utf-8) before anything trained; it prints escaped (`\\udcff`)."""
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def main(argv: list[str] | None = None, *, on_chunk=None) -> None:
    """Run the command line `argv` (default: this process's), e.g. `main(["train", "--env", "tmaze_5"])`. `on_chunk`:
    called with every chunk that the command trains (train, sweep, gap, benchmark; `pobax.train`'s `on_chunk`), e.g.
    to follow a command run from Python; the benchmark then trains in this process (one job)."""
    from pobax.eval import BenchmarkFailed
    from pobax.eval._interrupt import Terminated

    argv = sys.argv[1:] if argv is None else list(argv)
    _printable_streams()
    empty = _empty_argument(argv)
    if empty is not None:
        _error(f"{empty} is empty: give it a value (an unset shell variable?).")
    repeated = _repeated_list_flag(argv)
    if repeated is not None:
        flag, times = repeated
        example = "--axis hidden_size=8,16 num_envs=4,8" if flag == "--axis" else f"{flag} A B"
        _error(f"{flag} is given {times} times: give it once, with all its values ({example}); a later one would "
               f"replace the values of the first.")
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            cmd = tyro.extras.subcommand_cli_from_dict(COMMANDS, args=argv, description=__doc__)
    except ValueError as e:  # a type check of TrainConfig (e.g. a preset-like value given as a flag)
        _error(str(e))
    except SystemExit as e:  # tyro's error box, as one line
        if e.code in (0, None):
            sys.stderr.write(said.getvalue())
            raise
        _error(_one_line(said.getvalue(), argv), code=e.code if isinstance(e.code, int) else 2)
    sys.stderr.write(said.getvalue())
    sub = argv[1:] if argv else []
    try:
        _distributed(cmd)
    except ValueError as e:  # a UsageError, or init_distributed's
        _error(str(e))
    training = type(cmd) in (Train, Sweep, Gap, Benchmark)
    if type(cmd) is Benchmark and cmd.jobs != 1 and not cmd.dry_run:
        # Agents side by side (several GPUs) run in processes of their own: this one must not hold most of every
        # GPU's memory, as JAX's preallocation would once its backend starts (the next lines start it).
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if training:
        from pobax.agent import enable_compile_cache

        enable_compile_cache(accelerators_only=True)
    given = _given_fields(cmd, sub) if training else frozenset()
    handlers = {  # by the command's exact class (Sweep is a Train: an isinstance chain would depend on its order)
        Train: lambda: run_train(cmd, given, on_chunk), Sweep: lambda: run_sweep(cmd, given, on_chunk),
        Gap: lambda: run_gap(cmd, given, argv, on_chunk), Benchmark: lambda: run_benchmark(cmd, given, argv, on_chunk),
        Results: lambda: run_results(cmd),
        Plot: lambda: run_plot(cmd), Eval: lambda: run_eval(cmd), Render: lambda: run_render(cmd),
        Envs: lambda: run_envs(cmd),
    }
    try:
        handlers[type(cmd)]()
    except (KeyboardInterrupt, Terminated) as e:  # Ctrl-C, or a `kill` of jobs run side by side: how to continue
        _interrupted(cmd, e, argv)
    except BenchmarkFailed as e:  # agents trained side by side that failed; the others' results are written
        _error(str(e), 1)
    except BrokenPipeError:  # stdout's reader has gone (`pobax results | head -1`): `entrypoint` ends quietly
        raise
    except OSError as e:  # a file-system problem (a path, permissions, a full disk)
        _error(_os_error_line(e))
    except RuntimeError as e:  # XLA out of memory where the bound checked before compiling (a lower bound) passed
        first = str(e).splitlines()[0] if str(e) else ""
        if "RESOURCE_EXHAUSTED" not in first:
            raise
        lower = ("--episodes (played side by side, every run at once)" if type(cmd) is Eval else
                 "--num-envs, --hidden-size or the runs of one program (seeds × sets; `sweep --max-runs`)")
        _error(f"out of device memory ({first}); lower {lower}, or free the device; files already written are kept")
    except (ValueError, ImportError) as e:
        if not _raised_by_pobax(e):  # an internal error in the user's code (a memory cell): its traceback matters
            raise
        _error(str(e).splitlines()[0] if str(e) else type(e).__name__)  # bad input, a missing extra


def _raised_by_pobax(e: BaseException) -> bool:
    """Whether `e` was raised by pobax's own code (this file or the package): a refusal of bad input, which it says
    in a line, rather than an error inside code pobax calls (a user's memory cell, a library)."""
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is None:
        return True
    where = Path(tb.tb_frame.f_code.co_filename).resolve()
    return where == Path(__file__).resolve() or _PACKAGE in where.parents


_PACKAGE = Path(__import__("pobax").__file__).resolve().parent


def entrypoint() -> None:
    try:
        main()
    except BrokenPipeError:  # stdout's reader stopped early (`pobax train --help | head -1`): Python's recipe
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (the last flush at exit fails no more)
        raise SystemExit(1) from None
    except KeyboardInterrupt:  # before a command started (reading the command line)
        print("error: interrupted", file=sys.stderr)
        code = 130
    except SystemExit as e:
        if e.code not in (130, 143):
            raise
        code = e.code
    else:
        return
    # Ctrl-C or a kill: XLA may still be compiling or running in its threads, and tearing the interpreter down under
    # them can crash it (a segmentation fault instead of exit 130 or 143); every file is already written whole.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    entrypoint()
