"""Checkpoint/resume: an interrupted run continues to the same metrics, bit for bit; a checkpoint is one unit, so a
stop at any step of writing one leaves a run that resumes exactly or is refused; bad resumes fail clearly."""

import dataclasses
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pobax.eval._results as R
from pobax.agent import TrainConfig
from pobax.eval import CheckpointError, train

ROOT = Path(__file__).resolve().parents[1]
CFG = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2,
                  total_steps=4 * 16 * 6, num_seeds=2, lr=(2.5e-3, 2.5e-4), num_chunks=3, normalize_obs=True)


def _comparable(m: pd.DataFrame) -> pd.DataFrame:
    # chunks read back from CSV are float64 holding the float32 values written: compare in float32
    m = m.reset_index(drop=True)
    return m.astype({c: np.float32 for c in m.columns if m[c].dtype.kind == "f"})


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    path = tmp_path_factory.mktemp("full") / "run"
    return train(CFG, path, progress=False)


def test_resume_is_bit_exact(tmp_path, full):
    part = train(CFG, tmp_path / "split", progress=False, max_chunks=1)
    assert not part.summary["finished"]
    meta = json.loads((tmp_path / "split" / "checkpoint.json").read_text())
    assert meta["chunks_done"] == 1 and (tmp_path / "split" / meta["file"]).exists()
    assert not (tmp_path / "split" / "summary.json").exists()
    part = train(CFG, tmp_path / "split", progress=False, resume=True, max_chunks=1)  # a second interruption
    assert sorted(p.name for p in (tmp_path / "split").glob("checkpoint-*.eqx")) == ["checkpoint-00002.eqx"]
    resumed = train(CFG, tmp_path / "split", progress=False, resume=True)
    assert resumed.summary["finished"]
    pd.testing.assert_frame_equal(_comparable(full.metrics), _comparable(resumed.metrics), check_exact=True)
    for a, b in zip(np.asarray(full.state.model.actor.out.weight), np.asarray(resumed.state.model.actor.out.weight)):
        np.testing.assert_array_equal(a, b)
    # the files on disk are identical, byte for byte
    assert (tmp_path / "split" / "metrics.csv").read_bytes() == (full.run_dir / "metrics.csv").read_bytes()
    assert not list((tmp_path / "split").glob("checkpoint*"))  # finished runs keep their results, not the state
    # who trained what: three sessions (two interruptions), every chunk timed once, the wall time summed over them
    sessions = json.loads((tmp_path / "split" / "sessions.json").read_text())
    assert [s["from_chunk"] for s in sessions] == [0, 1, 2] and [len(s["chunks"]) for s in sessions] == [1, 1, 1]
    assert [s["from_chunk"] for s in resumed.summary["sessions"]] == [0, 1, 2]
    assert all(s["device"] and s["jax"] for s in resumed.summary["sessions"])
    timing = pd.read_csv(tmp_path / "split" / "timing.csv")
    assert timing["chunk"].tolist() == [0, 1, 2] and timing["session"].tolist() == [0, 1, 2]
    assert resumed.summary["wall_s"] == pytest.approx(timing["seconds"].sum())


def test_metrics_file_does_not_depend_on_chunking_or_timing(tmp_path, full):
    """Two identical runs give byte-identical metrics.csv, whatever `num_chunks` (no wall-clock column)."""
    again = train(dataclasses.replace(CFG, num_chunks=2), tmp_path / "again", progress=False)
    assert (again.run_dir / "metrics.csv").read_bytes() == (full.run_dir / "metrics.csv").read_bytes()
    assert "seconds" in (again.run_dir / "timing.csv").read_text()


STEPS = ("state written", "state renamed", "manifest written", "manifest renamed", "previous state removed")

# A resumed training of one chunk, killed (SIGKILL) at the system call that does `stop`'s step of writing the
# checkpoint (a rename: before it; "... renamed", "... removed": at the process's next audited operation after it).
# Python's audit events name each rename and removal as it is made. The programs come from a compilation cache
# that the first of these processes fills.
KILLED_AT = """
import json, os, signal, sys, threading
from pathlib import Path

from pobax.agent import config_from_dict, enable_compile_cache
from pobax.eval import train

run, stop, cfg = Path(sys.argv[1]), sys.argv[2], config_from_dict(json.loads(sys.argv[3]))
enable_compile_cache(sys.argv[4])
main, armed = threading.get_ident(), False


def kill_at(event, args):
    global armed
    if threading.get_ident() != main:
        return
    if armed:  # the first operation after the step (os.kill is one too: disarmed first)
        armed = False
        os.kill(os.getpid(), signal.SIGKILL)
    if event not in ("os.rename", "os.remove"):
        return
    name = Path(args[1] if event == "os.rename" else args[0]).name
    what = "state" if name.startswith("checkpoint-") else "manifest" if name == "checkpoint.json" else None
    if event == "os.rename" and stop == f"{what} written":
        os.kill(os.getpid(), signal.SIGKILL)  # before the rename: the temporary file is written
    armed = stop == (f"{what} renamed" if event == "os.rename" else f"previous {what} removed")


sys.addaudithook(kill_at)
train(cfg, run, progress=False, resume=True, max_chunks=1)
if armed:
    os.kill(os.getpid(), signal.SIGKILL)  # nothing after the step: killed as the process ends
sys.exit(f"never reached: {stop}")
"""


@pytest.fixture(scope="module")
def compile_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("xla")


@pytest.mark.parametrize("stop", [s if s in ("state written", "previous state removed") else  # the rest: -m slow
                                  pytest.param(s, marks=pytest.mark.slow) for s in STEPS])
def test_a_kill_at_any_write_of_a_checkpoint_resumes_exactly(tmp_path, full, compile_cache, stop):
    """Writing the checkpoint after chunk 2 takes five steps on disk: the state written to a temporary file, renamed
    to its own name; the manifest (checkpoint.json: the chunk count, the state's name and hash) written to a temporary
    file, renamed over the previous one; the previous state removed. A process is killed after each step (its
    temporary files stay), and the resume gives the uninterrupted run's metrics, byte for byte, and leaves no stray
    file."""
    run = tmp_path / "run"
    train(CFG, run, progress=False, max_chunks=1)
    config = json.dumps(dataclasses.asdict(CFG))
    killed = subprocess.run([sys.executable, "-c", KILLED_AT, str(run), stop, config, str(compile_cache)], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    done = json.loads((run / "checkpoint.json").read_text())["chunks_done"]
    assert done == (2 if stop in ("manifest renamed", "previous state removed") else 1)
    assert bool(list(run.glob(".*.tmp"))) == stop.endswith("written")
    resumed = train(CFG, run, progress=False, resume=True)
    assert resumed.summary["finished"]
    assert (run / "metrics.csv").read_bytes() == (full.run_dir / "metrics.csv").read_bytes()
    assert not list(run.glob(".*.tmp")) and not list(run.glob("checkpoint*"))
    # a chunk trained again is timed once: the stopped session keeps only what its checkpoint counted
    assert pd.read_csv(run / "timing.csv")["chunk"].tolist() == [0, 1, 2]
    assert [s["from_chunk"] for s in resumed.summary["sessions"]] == ([0, 1, 2] if done == 2 else [0, 1])


def test_a_checkpoint_that_disagrees_with_its_manifest_is_refused(tmp_path):
    """The reproduction of a real failure: a state newer than the chunk count beside it trained a chunk twice. The
    manifest holds the state's hash, so any such mix is refused, and nothing is written."""
    run = tmp_path / "run"
    train(CFG, run, progress=False, max_chunks=1)
    old_meta = (run / "checkpoint.json").read_text()
    old_state = (run / "checkpoint-00001.eqx").read_bytes()
    train(CFG, run, progress=False, resume=True, max_chunks=1)
    (run / "checkpoint.json").write_text(old_meta)  # the chunk count of chunk 1 ...
    (run / "checkpoint-00001.eqx").unlink(missing_ok=True)
    (run / "checkpoint-00002.eqx").rename(run / "checkpoint-00001.eqx")  # ... beside the state after chunk 2
    before = {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with pytest.raises(CheckpointError, match="SHA-256"):
        train(CFG, run, progress=False, resume=True)
    assert {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    assert old_state != before["checkpoint-00001.eqx"]


def test_resuming_a_folder_of_runs_or_a_sweep_says_what_to_pass_instead(tmp_path, capsys):
    """`--resume` on a folder of runs or a sweep's directory said only "not a run directory": it now names the runs
    below it, or the command that continues the sweep (`pobax sweep` again with the same --out)."""
    import cli

    train(CFG, tmp_path / "runs" / "a", progress=False, max_chunks=1)
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "pobax-sweep.json").write_text("{}")
    for where, hint in ((tmp_path / "runs", "it holds 1 run directory below it"),
                        (tmp_path / "sweep", "it is a `pobax sweep` directory (pobax-sweep.json): run the same")):
        with pytest.raises(CheckpointError, match="nothing to resume; " + re.escape(hint)):
            train(CFG, where, progress=False, resume=True)
        with pytest.raises(SystemExit) as e:
            cli.main(["train", "--resume", str(where)])
        err = capsys.readouterr().err
        assert e.value.code == 2 and hint in err and err.count("\n") == 1, err


def test_bad_resumes_fail_clearly_and_keep_files(tmp_path):
    with pytest.raises(CheckpointError, match="not a run directory"):
        train(CFG, tmp_path / "nothing", progress=False, resume=True)
    train(CFG, tmp_path / "run", progress=False, max_chunks=1)
    before = sorted(p.name for p in (tmp_path / "run").rglob("*"))
    other = dataclasses.replace(CFG, hidden_size=16)
    with pytest.raises(CheckpointError, match="hidden_size"):
        train(other, tmp_path / "run", progress=False, resume=True)
    ckpt = tmp_path / "run" / "checkpoint-00001.eqx"
    data = bytearray(ckpt.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside the state
    ckpt.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="corrupted"):
        train(CFG, tmp_path / "run", progress=False, resume=True)
    assert sorted(p.name for p in (tmp_path / "run").rglob("*")) == before
    assert ckpt.read_bytes() == bytes(data)  # nothing was overwritten


def test_a_run_being_trained_is_refused_to_a_second_process(tmp_path):
    """While one process trains (or resumes) a run directory, another is refused before it reads or writes
    anything; once the first ends, however it ended, the run resumes. A second process's view: a lock held
    elsewhere (flock conflicts between two opens of the directory, also within one process)."""
    import sys

    pytest.importorskip("fcntl")
    run = tmp_path / "run"
    train(CFG, run, progress=False, max_chunks=1)
    before = {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    other = R.RunDir(run)
    other.hold()  # another trainer
    with pytest.raises(R.RunDirBusyError, match="being trained by another process"):
        train(CFG, run, progress=False, resume=True)
    assert {p.name: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    other.release()
    # a holder killed outright (SIGKILL: no cleanup) leaves no lock behind
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; d = os.open(sys.argv[1], "
                               "os.O_RDONLY); fcntl.flock(d, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
                               str(run)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(R.RunDirBusyError):
        train(CFG, run, progress=False, resume=True)
    holder.kill()
    holder.wait()
    done = train(CFG, run, progress=False, resume=True)
    assert done.summary["finished"]
    R.RunDir(run).hold()  # nothing left held by the finished training
