"""What the hostile-user tests share (`test_hostile.py`, `test_hostile_inputs.py`): a tiny T-Maze 5 configuration
for the CPU (its runs `stopped` and `finished`, and the misbehaving `user_cells`, are conftest.py's fixtures) and
`refused`, the check that a command line is one line of error and exit 2."""

import subprocess
from pathlib import Path

import jaxtyping
import pytest

import cli
from pobax.agent import TrainConfig
from pobax.eval import train  # noqa: F401  (conftest.py's fixtures train with it)

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--env", "tmaze_5", "--hidden-size", "8", "--total-steps", "4096", "--num-seeds", "2", "--fast-compile",
        "--quiet"]
CFG = TrainConfig(env="tmaze_5", hidden_size=8, total_steps=4096, num_seeds=2, fast_compile=True)


def digest(path: Path) -> dict:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def refused(capsys, args, *messages: str, code: int = 2, started: bool = False, on_chunk=None) -> str:
    """The command line, run in this process, is refused: one line on stderr holding `messages`, nothing on stdout
    (but the run directory it announced, where it `started` training). `on_chunk`: as `cli.main`'s."""
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args], on_chunk=on_chunk)
    out, err = capsys.readouterr()
    assert e.value.code == code, err
    assert all(m in err for m in messages), err
    assert err.strip().count("\n") == 0 and "Traceback" not in err, err
    assert out == ("" if not started else f"run directory: {args[args.index('--resume') + 1]}\n"), out
    return err


def copy(src: Path, dst: Path) -> Path:
    subprocess.run(["cp", "-r", str(src), str(dst)], check=True)
    return dst


def write_summary(run: Path, summary: dict) -> None:
    """Write `summary` into the finished run `run` as pobax would have (sealed with the run's files as they are now):
    a summary that training itself could have left, unlike a hand edit, which the seal refuses."""
    from pobax.eval._files import write_json
    from pobax.eval._seal import seal_summary

    write_json(run / "summary.json", seal_summary(summary, run))


def pre_seal(summary: dict) -> dict:
    """`summary` as a pobax from before summaries were sealed wrote it: no seal, and sessions that do not say
    their pobax seals (a summary whose sessions say so and has no seal is refused: its seal was removed)."""
    from pobax.eval._seal import SEALS, without_seal

    sessions = [{k: v for k, v in s.items() if k != SEALS} for s in summary.get("sessions", [])]
    return {**without_seal(summary), "sessions": sessions}


def unseal(run: Path) -> None:
    """Make the finished run `run` read as one trained before summaries were sealed (`pre_seal`, and its
    sessions.json likewise), so that a reader's own checks of its files, behind the seal, are what answers."""
    import json

    from pobax.eval._seal import SEALS

    (run / "summary.json").write_text(json.dumps(pre_seal(json.loads((run / "summary.json").read_text()))))
    sessions = json.loads((run / "sessions.json").read_text())
    (run / "sessions.json").write_text(json.dumps([{k: v for k, v in s.items() if k != SEALS} for s in sessions]))


@pytest.fixture
def as_a_notebook():
    """The calls as a notebook makes them: without the test suite's jaxtyping checks, which refuse a Python value
    where the annotations say otherwise before pobax's own checks are reached. A module that calls the API as a
    notebook does imports it and applies it to every test (`pytestmark = pytest.mark.usefixtures(...)`)."""
    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", False)
