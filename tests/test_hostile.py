"""The README's "Runs are results or refusals", tried as a hostile but fair user would: two processes on one run
directory, edited or damaged run directories, numbers too large to represent or to fit, malformed records, a killed
benchmark, user cells that misbehave, and every subcommand on what that leaves. Tiny T-Maze 5 runs on the CPU."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import cli
from pobax.agent import TrainConfig
from pobax.env import AbstractWrapper, make
from pobax.eval import RunDir, load_run, train
from pobax.eval._files import CheckpointError, shared_files
from pobax.eval._listing import list_runs
from pobax.eval._plan import BenchmarkError, benchmark_dir
from pobax.eval._report import write_results

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


@pytest.fixture(scope="module")
def stopped(tmp_path_factory) -> Path:
    """A run stopped after 3 of its 8 chunks (resumable)."""
    run = tmp_path_factory.mktemp("hostile") / "stopped"
    train(CFG, run, progress=False, max_chunks=3)
    return run


@pytest.fixture(scope="module")
def finished(tmp_path_factory, stopped) -> Path:
    run = copy(stopped, tmp_path_factory.mktemp("hostile") / "finished")
    train(CFG, run, progress=False, resume=True)
    return run


# --- 1. one process per run directory -------------------------------------------------------------------------

def test_two_processes_on_one_new_out_the_second_is_refused(tmp_path, capsys):
    out = tmp_path / "TW"
    first = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "train", *TINY, "--out", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                             env={**os.environ, "JAX_PLATFORMS": "cpu"})
    deadline = time.monotonic() + 120
    while not (out / "config.json").exists():  # the first has taken the directory
        assert first.poll() is None and time.monotonic() < deadline, first.communicate()
        time.sleep(0.05)
    refused(capsys, ["train", *TINY, "--lr", "1e-3", "--out", out], "being trained by another process")
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    saved = RunDir(out).read_config()["config"]
    assert saved["lr"] == [2.5e-4] and saved["total_steps"] == 4096  # the first's configuration, and its results
    assert set(RunDir(out).metrics()["lr"]) == {2.5e-4} and (out / "summary.json").exists()


def test_a_directory_holding_another_configurations_config_json_is_refused(tmp_path, capsys):
    out = tmp_path / "r"
    RunDir.create(out, {"config": json.loads(json.dumps(CFG.__dict__ | {"lr": (1e-3,)})),
                        "hyperparameter_sets": []}).release()  # a run stopped before its first chunk
    before = digest(out)
    refused(capsys, ["train", *TINY, "--out", out], "another configuration (differs in: lr)")
    assert digest(out) == before


def test_writers_of_one_benchmark_directory_wait_for_each_other(tmp_path):
    """The shared files of an --out (benchmark.json, the tables) are read, changed and written under one lock: a
    process writing the tables waits while another holds them."""
    out = tmp_path / "out"
    out.mkdir()
    done = threading.Event()
    with shared_files(out):
        writer = threading.Thread(target=lambda: (write_results(out), done.set()))
        writer.start()
        assert not done.wait(1.0) and not (out / "benchmark.csv").exists()  # waiting, nothing written
    writer.join(60)
    assert done.is_set() and (out / "benchmark.csv").exists()


def test_a_new_out_that_another_benchmark_is_starting_in_is_not_refused(tmp_path):
    """Another process starting into the same new --out has made its lock and temporary files, not yet benchmark.json:
    that directory is still new; a directory holding anything else is not an output directory."""
    out = tmp_path / "out"
    out.mkdir()
    for name in (".benchmark.lock", ".write-check.x1.tmp", ".benchmark.json.ab12.tmp"):
        (out / name).write_text("")
    assert benchmark_dir(out) == out
    (out / "notes.txt").write_text("mine")
    with pytest.raises(BenchmarkError, match="holds other files and no benchmark.json"):
        benchmark_dir(out)


@pytest.mark.slow
def test_benchmarks_of_other_environments_into_one_out_at_once_keep_every_call_and_row(tmp_path):
    """Six processes training six environments into one --out at once: every call is in benchmark.json and every
    record a row of benchmark.csv (without the lock, 4-5 of 6 survived the read-change-write races)."""
    envs = [f"tmaze_{n}" for n in range(5, 11)]
    procs = [subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "benchmark", "--envs", env, "--agents", "floor",
                               "--budget", "smoke", "--quiet", "--out", str(tmp_path / "out")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                              env={**os.environ, "JAX_PLATFORMS": "cpu"}) for env in envs]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    meta = json.loads((tmp_path / "out" / "benchmark.json").read_text())
    assert sorted(c["envs"][0] for c in meta["calls"]) == sorted(envs) and sorted(meta["envs"]) == sorted(envs)
    rows = (tmp_path / "out" / "benchmark.csv").read_text().splitlines()[1:]
    assert sorted(r.split(",")[0] for r in rows) == sorted(envs)


# --- 2. a resume trains exactly what the run started with -----------------------------------------------------

@pytest.mark.parametrize("field, value", [("lr", [0.5]), ("total_steps", 8192), ("anneal_lr", False)])
def test_a_resume_with_an_edited_config_json_is_refused(tmp_path, stopped, capsys, field, value):
    run = copy(stopped, tmp_path / "r")
    record = json.loads((run / "config.json").read_text())
    record["config"][field] = value
    (run / "config.json").write_text(json.dumps(record))
    before = digest(run)
    refused(capsys, ["train", "--resume", run], "differs from the configuration the run started with in " + field)
    assert digest(run) == before


# --- 3. a resume verifies the chunks it builds on -------------------------------------------------------------

@pytest.mark.parametrize("damage, message", [
    (lambda r: (r / "metrics" / "00001.csv").write_text("garbage\n"), "metrics/00001.csv' is damaged"),
    (lambda r: (r / "metrics" / "00001.csv").write_text(""), "metrics/00001.csv' is damaged"),
    (lambda r: (r / "checkpoint.json").write_text((r / "checkpoint.json").read_text().replace(
        '"chunks_done": 3', '"chunks_done": 2')), "checkpoint.json was edited"),
    (lambda r: _unhash(r), "checkpoint.json was edited"),  # its hashes removed, then a chunk edited: was trained on
])
def test_a_resume_refuses_damaged_chunks_naming_the_file(tmp_path, stopped, capsys, damage, message):
    run = copy(stopped, tmp_path / "r")
    damage(run)
    before = digest(run)
    refused(capsys, ["train", "--resume", run], message)
    assert digest(run) == before


def _unhash(run: Path) -> None:
    """checkpoint.json without its own and its chunks' SHA-256 (as if older), then a chunk's return edited."""
    manifest = json.loads((run / "checkpoint.json").read_text())
    del manifest["manifest_sha256"], manifest["metrics_sha256"]
    (run / "checkpoint.json").write_text(json.dumps(manifest))
    chunk = run / "metrics" / "00001.csv"
    lines = chunk.read_text().splitlines(True)
    header, row = lines[0].rstrip("\n").split(","), lines[1].rstrip("\n").split(",")
    row[header.index("return")] = "99.0"
    chunk.write_text("".join([lines[0], ",".join(row) + "\n", *lines[2:]]))


@pytest.mark.parametrize("source, damage", [("stopped", "checkpoint.json"), ("finished", "summary.json")])
def test_a_resume_of_a_run_that_lost_its_checkpoint_json_or_summary_is_refused(tmp_path, stopped, finished, capsys,
                                                                             source, damage):
    """A run past its first checkpoint without checkpoint.json (or a finished one without summary.json) was trained
    again from the start, its chunks, checkpoint, model and sessions written over; now refused, nothing changed."""
    run = copy(stopped if source == "stopped" else finished, tmp_path / "r")
    (run / damage).unlink()
    before = digest(run)
    refused(capsys, ["train", "--resume", run], "has trained past a checkpoint", "but has no checkpoint.json")
    assert digest(run) == before


def test_a_lock_no_file_in_the_run_directory_can_take_away(tmp_path, stopped, capsys):
    """The run directory itself is locked: deleting a lock file beside the run's let a second process train it."""
    run = copy(stopped, tmp_path / "r")
    holder = RunDir(run)
    holder.hold()
    try:
        for p in run.iterdir():
            if p.name.startswith("."):
                p.unlink()
        refused(capsys, ["train", "--resume", run], "being trained by another process")
    finally:
        holder.release()


def test_a_rerun_refuses_a_finished_runs_summary_json_of_another_shape(tmp_path, finished):
    """sweep, gap and benchmark reuse a finished run from its summary.json: one edited into another shape was a
    KeyError or TypeError traceback in the selection; now refused naming it."""
    from pobax.eval._records import RecordError
    from pobax.eval._run import train_or_reuse

    run = copy(finished, tmp_path / "r")
    for text in ('{"x": 1}', "[1]", '{"sets": [{}]}'):
        (run / "summary.json").write_text(text)
        with pytest.raises(RecordError, match="summary.json' is not a run's summary pobax wrote"):
            train_or_reuse(CFG, run, progress=False)
        assert (run / "summary.json").read_text() == text


def _drop(path: Path, session: int, chunk: int, key: str | None = None) -> None:
    """Edit sessions.json: remove a chunk's entry (or only its `key`)."""
    sessions = json.loads(path.read_text())
    if key is None:
        del sessions[session]["chunks"][chunk]
    else:
        del sessions[session]["chunks"][chunk][key]
    path.write_text(json.dumps(sessions))


@pytest.mark.parametrize("damage", [
    lambda r: (r / "sessions.json").unlink(),  # was resumed, its first chunks' device, commit and times lost
    lambda r: (r / "sessions.json").write_text('{"a": 1}'),  # was a TypeError traceback
    lambda r: _drop(r / "sessions.json", 0, 1),
    lambda r: _drop(r / "sessions.json", 0, 2, "seconds"),  # was a KeyError once the run finished
])
def test_a_resume_refuses_a_sessions_json_that_lost_the_chunks_it_builds_on(tmp_path, stopped, capsys, damage):
    """sessions.json says which device, JAX and commit trained each chunk (and how long it took): a resume whose
    checkpoint counts 3 chunks refuses one that no longer records them, naming it, and changes nothing."""
    run = copy(stopped, tmp_path / "r")
    damage(run)
    before = digest(run)
    refused(capsys, ["train", "--resume", run], f"{str(run / 'sessions.json')!r} does not record the sessions that "
                                                "trained chunks 0 … 2")
    assert digest(run) == before


@pytest.mark.parametrize("text", ["[1]", '{"config": [1], "hyperparameter_sets": []}', '{"configuration": {}}'])
def test_a_config_json_of_another_shape_is_refused_by_every_command(tmp_path, stopped, finished, capsys, text):
    """Valid JSON of another shape in config.json: each command refuses it in a line naming it (resume, eval and plot
    ended in AttributeError, TypeError or KeyError tracebacks)."""
    for src, commands in ((stopped, [["train", "--resume", "{run}"]]),
                          (finished, [["eval", "{run}", "--episodes", "2"], ["plot", "{run}", "--out", "{tmp}/c.png"],
                                      ["render", "{run}", "--out", "{tmp}/e.gif"]])):
        run = copy(src, tmp_path / src.name)
        (run / "config.json").write_text(text)
        before = digest(run)
        for command in commands:
            refused(capsys, [a.format(run=run, tmp=tmp_path) for a in command],
                    f"{str(run / 'config.json')!r} is not a run configuration pobax wrote")
        assert digest(run) == before
    assert not list(tmp_path.glob("c.png")) and not list(tmp_path.glob("e.*"))


def test_plot_labels_from_the_configuration_not_an_edited_list_of_sets(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    record = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**record, "hyperparameter_sets": []}))  # was an IndexError
    cli.main(["plot", str(run), "--best", "--json", str(tmp_path / "c.json"), "--out", str(tmp_path / "c.png")])
    assert list(json.loads((tmp_path / "c.json").read_text())["curves"]) == [
        "tmaze_5 partial gru (lr=0.00025, λ0=0.95)"]


@pytest.mark.parametrize("cut, message", [(lambda t: "".join(t.splitlines(True)[:9]), "holds 8 rows, not one per "
                                           "update of each of the run's 2 runs (8 updates each)"),
                                          (lambda t: t[:-30], "its last line is cut short")])
def test_a_finished_runs_metrics_csv_cut_short_is_refused(tmp_path, finished, capsys, cut, message):
    """A finished run's metrics.csv cut short (a copy interrupted, a full disk): plot drew the curves of the rows left
    and load_run returned them; both refuse it, naming the file."""
    run = copy(finished, tmp_path / "r")
    (run / "metrics.csv").write_text(cut((run / "metrics.csv").read_text()))
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], f"{str(run / 'metrics.csv')!r}", message)
    with pytest.raises(ValueError) as e:
        load_run(run)
    assert message in str(e.value)
    assert not (tmp_path / "c.png").exists()


# --- 4. numbers the program cannot represent, or memory it cannot have -----------------------------------------

@pytest.mark.parametrize("args, message", [
    (["--hidden-size", "1000000000"], "--hidden-size 1000000000: the runs need at least"),
    (["--num-seeds", "1000000000"], "--num-seeds 1,000,000,000"),
    (["--num-seeds", "100000000"], "--num-seeds 100000000: the runs need at least"),
    (["--total-steps", "1099511627776"], "--total-steps 1,099,511,627,776 is 2,147,483,648 updates"),
    (["--vf-coeff", "1e39"], "--vf-coeff values must be >= 0.0 and finite, got 1e+39 (inf in float32"),
    (["--lr", "1e-50"], "--lr values must be in (0.0, 1.0] and finite, got 1e-50 (0 in float32"),
    (["--num-envs", "4294967296", "--num-minibatches", "1"], "--num-envs must be a positive integer of at most"),
    (["--seed", "4294969316"], "--seed must be an integer in [0, 4294967295]"),  # 2020 + 2**32: would alias 2020
    (["--seed", "-1"], "--seed must be an integer in [0, 4294967295]"),
])
def test_numbers_too_large_are_refused_naming_the_flag(tmp_path, capsys, args, message):
    refused(capsys, ["train", *TINY, *args, "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("args, message", [
    (["--embed-size", "1000000000"], "--embed-size 1000000000: the runs need at least"),  # was an abort, run dir left
    (["--qkv-features", "1000000000"], "--qkv-features 1000000000: the runs need at least"),  # RESOURCE_EXHAUSTED
    (["--window-mem", "2000000000"], "--window-mem 2000000000: the runs need at least"),  # RESOURCE_EXHAUSTED
    (["--num-layers", "2000000000"], "--num-layers 2000000000: the runs need at least"),  # hung building the layers
])
def test_transformer_xl_sizes_beyond_memory_are_refused(tmp_path, capsys, args, message):
    refused(capsys, ["train", *TINY, "--memory", "trxl", *args, "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()


def test_eval_max_steps_beyond_int32_is_refused(stopped, capsys):
    before = digest(stopped)
    for steps in (str(2**31), str(10**11)):  # was an OverflowError traceback
        refused(capsys, ["eval", stopped, "--max-steps", steps], "--max-steps must be a positive integer of at most "
                                                                 "2,147,483,647")
    assert digest(stopped) == before


def test_every_program_of_a_sweep_gap_or_benchmark_is_checked_before_the_first_trains(tmp_path, capsys):
    """A structural axis, an agent or a sweep beyond memory, and counts of 0: refused before anything is written (the
    sweep trained its first program, gap and benchmark their first agents, then refused, leaving their --out)."""
    sweep = ["sweep", *TINY, "--lr", "1e-3", "2e-3", "--out", tmp_path / "s"]
    refused(capsys, [*sweep, "--max-runs", "0"], "--max-runs must be a positive integer")  # was run as 1
    refused(capsys, [*sweep, "--axis", "hidden_size=8,1000000000"], "--hidden-size 1000000000: the runs need")
    gap = ["gap", *TINY, "--agents", "floor", "gru", "--out", tmp_path / "g"]
    refused(capsys, [*gap, "--sweep", "--sweep-seeds", "0"], "--sweep-seeds must be a positive integer, got 0")
    refused(capsys, [*gap, "--sweep", "--sweep-seeds", "1000000000"], "--sweep-seeds 1,000,000,000: --num-seeds")
    refused(capsys, [*gap, "--num-seeds", "100000000"], "--num-seeds 100000000: the runs need at least")
    bench = ["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--quiet", "--out", tmp_path / "b"]
    refused(capsys, [*bench, "--agents", "floor", "trxl", "--embed-size", "1000000000"],
            "tmaze_5 / trxl: --embed-size 1000000000: the runs need at least")
    refused(capsys, [*bench, "--agents", "floor", "--protocol", "paper", "--hidden-size", "100000"],
            "tmaze_5 / floor: --hidden-size 100000: the runs need at least")
    assert not any((tmp_path / d).exists() for d in ("s", "g", "b"))


@pytest.mark.parametrize("env, message", [
    ("tmaze_99999999999", "T-Maze needs a hallway length in [1, 2**31 - 3], got 99999999999"),  # was a traceback
    ("rocksample_100000_3", "RockSample needs a size in [2, 46340]"),  # used to build a list of 10**10 cells
    ("battleship_100000", "Battleship's placement tables for a 100000x100000 board take"),  # used to hang
])
def test_environment_ids_too_large_to_build_are_refused(tmp_path, capsys, env, message):
    refused(capsys, ["train", "--env", env, *TINY[2:], "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()


def test_a_large_rocksample_grid_costs_no_table_of_its_cells():
    """RockSample's rock lookup is over its rocks, not a size² table: a 46340×46340 grid (the largest whose cells
    int32 indexes) builds in little memory, steps, and samples the rock under the agent."""
    env = make("rocksample_46340_3", wrappers=False)
    assert all(leaf.size < 10 for leaf in jax.tree.leaves(eqx.filter(env, eqx.is_array)))
    state, _ = env.reset(key=jax.random.key(0))
    state = dataclasses.replace(state, pos=env.rock_positions[1], rock_good=jax.numpy.ones(3, bool))
    state, ts = env.step(state, jax.numpy.asarray(4), key=jax.random.key(1))  # SAMPLE on rock 1, good
    assert float(ts.reward) == 10.0 and state.rock_good.tolist() == [True, False, True]


@pytest.mark.parametrize("args, message", [
    (["train", "--env", "rocksample_5_3", *TINY[2:], "--env-options", f"map_seed={2**64}"],  # would alias map_seed 0
     "RockSample's map_seed must be an integer in [0, 2**64 - 1], got 18446744073709551616"),
    (["train", "--env", "rocksample_5_3", *TINY[2:], "--env-options", "map_seed=-1"],
     "map_seed must be an integer in [0, 2**64"),
    (["benchmark", "--envs", "rocksample_5_3", "tmaze_5", "--budget", "smoke", "--env-options", "map_seed=3"],
     "Bad parameter for environment 'tmaze_5'"),  # refused before the first environment trains
    (["benchmark", "--envs", "tmaze_5", "--protocol", "paper", "--budget", "smoke", "--num-seeds", "0"],
     "--num-seeds must be a positive integer"),  # the protocol's evaluation seeds
])
def test_environment_options_and_evaluation_seeds_out_of_range_are_refused(tmp_path, capsys, args, message):
    refused(capsys, [*args, "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_more_jobs_than_programs_run_one_process_per_program(tmp_path):
    """--jobs 10**12 for two agents: two processes (it used to build 10**12 job slots, and hung)."""
    cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "ceiling", "--budget", "smoke", "--quiet",
              "--jobs", str(10**12), "--out", str(tmp_path / "out")])
    assert sorted(p.name for p in (tmp_path / "out" / "agents" / "tmaze_5").iterdir()) == ["ceiling.json",
                                                                                          "floor.json"]


def test_eval_episodes_beyond_memory_are_refused(stopped, capsys):
    before = digest(stopped)
    refused(capsys, ["eval", stopped, "--episodes", "1000000000"], "--episodes 1,000,000,000:")
    refused(capsys, ["eval", stopped, "--episodes", "4294967296"], "--episodes 4,294,967,296 is more than")
    # seeds of evaluation and rendering are 32-bit, as training's: -1 used to play other keys' episodes, 2**64 to
    # end in an OverflowError traceback
    for seed in ("-1", str(2**64)):
        refused(capsys, ["eval", stopped, "--seed", seed], "--seed must be an integer in [0, 4294967295]")
        refused(capsys, ["render", stopped, "--seed", seed, "--out", stopped / "x.gif"], "--seed must be an integer")
        refused(capsys, ["render", "--env", "Navix-DMLab-Maze-01-v0", "--seed", seed, "--steps", "2", "--out",
                         stopped / "x.png"], "--seed must be an integer")
    assert digest(stopped) == before


@pytest.mark.parametrize("seeds, message", [
    ("-1", "--rerun-seeds must be 0 (no re-run) or a positive integer"),
    ("100000000000", "--rerun-seeds must be 0 (no re-run) or a positive integer"),
    ("600000000", "--rerun-seeds 600,000,000: --num-seeds 600,000,000 × --num-envs 4"),
])
def test_a_sweeps_rerun_out_of_range_is_refused_before_the_sweep_trains(tmp_path, capsys, seeds, message):
    refused(capsys, ["sweep", *TINY, "--lr", "2.5e-3", "2.5e-4", "--rerun-seeds", seeds, "--out", tmp_path / "s"],
            message)  # (it used to train the whole sweep first)
    assert not (tmp_path / "s").exists()


# --- 5. benchmark --merge checks every record before copying ---------------------------------------------------

def test_merge_of_a_malformed_record_copies_nothing(tmp_path, capsys):
    src = tmp_path / "src"
    (src / "agents" / "tmaze_5").mkdir(parents=True)
    (src / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    (src / "agents" / "tmaze_5" / "gru.json").write_text('{"nope": 1}')
    refused(capsys, ["benchmark", "--merge", src, "--out", tmp_path / "out"],
            "gru.json' is not a benchmark record pobax wrote (no env, agent")
    assert not (tmp_path / "out").exists()


def test_merge_into_an_out_with_a_damaged_record_copies_nothing(tmp_path, capsys):
    """--out's own records are checked with the sources' before anything is copied (a source's record was copied,
    and benchmark.json rewritten, before --out's damaged one was refused)."""
    src = tmp_path / "src"
    cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--quiet", "--out", str(src)])
    capsys.readouterr()
    out = tmp_path / "out"
    (out / "agents" / "tmaze_5").mkdir(parents=True)
    (out / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    for text in ("garbage", '{"env": 5}'):
        (out / "agents" / "tmaze_5" / "gru.json").write_text(text)
        before = digest(out)
        refused(capsys, ["benchmark", "--merge", src, "--out", out], "gru.json'")
        assert digest(out) == before


def test_an_edited_record_is_refused_naming_it_before_anything_is_written(tmp_path, capsys):
    """A record edited into another shape: a benchmark into its directory, of its environment or another, is refused
    in a line naming it (it used to end in a KeyError at the tables), and nothing is written."""
    out = tmp_path / "out"
    cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--quiet", "--out", str(out)])
    capsys.readouterr()
    record = out / "agents" / "tmaze_5" / "floor.json"
    original = json.loads(record.read_text())
    for edit, what in ((lambda r: {"env": 5}, "(no agent, observability"),
                       (lambda r: {**r, "config": None}, "(config is None)"),
                       (lambda r: {**r, "disc": {**r["disc"], "mean": "high"}}, "(disc is not a mean")):
        record.write_text(json.dumps(edit(original)))
        before = digest(out)
        for env in ("tmaze_5", "tmaze_6"):
            refused(capsys, ["benchmark", "--envs", env, "--agents", "floor", "--budget", "smoke", "--out", out],
                    f"{str(record)!r} is not a benchmark record pobax wrote", what)
        assert digest(out) == before


@pytest.mark.parametrize("text, what", [("[]", "(a JSON list, not an object)"), ("{}", "(envs is not a list"),
                                        ('{"envs": [], "calls": 3}', "(calls is not a list of calls)"),
                                        ('{"envs": [], "calls": [], "protocol": 7}', "(protocol is 7)")])
def test_an_edited_benchmark_json_is_refused_naming_it(tmp_path, capsys, text, what):
    out = tmp_path / "out"
    out.mkdir()
    (out / "benchmark.json").write_text(text)
    message = f"{str(out / 'benchmark.json')!r} is not a benchmark.json pobax wrote"
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--dry-run", "--out", out], message, what)
    refused(capsys, ["benchmark", "--merge", out, "--out", tmp_path / "m"], message, what)
    assert (out / "benchmark.json").read_text() == text and not (tmp_path / "m").exists()


def test_an_edited_sweep_part_summary_is_refused_naming_it(tmp_path, capsys):
    """A finished sweep part whose summary.json was edited into another shape (valid JSON): the protocol's
    selection and `--merge` refuse it in a line naming the file, and nothing is written."""
    bench = ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--protocol", "paper", "--budget", "smoke",
             "--part-steps", "600", "--quiet", "--out", tmp_path / "p"]
    cli.main([str(a) for a in bench])
    capsys.readouterr()
    (tmp_path / "p" / "agents" / "tmaze_5" / "floor.json").unlink()  # the record again, from the parts
    part = sorted((tmp_path / "p" / "runs" / "tmaze_5" / "floor-sweep").iterdir())[0]
    summary = json.loads((part / "summary.json").read_text())
    for edit, what in ((lambda s: {"sets": []}, "(no sets)"),
                       (lambda s: {**s, "sets": [{**s["sets"][0], "lambda0": "high"}]}, "set 0 has a hyperparameter"),
                       (lambda s: {**s, "sets": [{**s["sets"][0], "disc_return_auc": {}}]}, "a return without")):
        (part / "summary.json").write_text(json.dumps(edit(summary)))
        before = digest(tmp_path / "p" / "runs"), digest(tmp_path / "p" / "agents")
        refused(capsys, bench, f"{str(part / 'summary.json')!r} is not a sweep part's summary pobax wrote", what)
        refused(capsys, ["benchmark", "--merge", tmp_path / "p", "--out", tmp_path / "m"], what)
        assert (digest(tmp_path / "p" / "runs"), digest(tmp_path / "p" / "agents")) == before  # runs and records
        assert not (tmp_path / "m").exists()


# --- 6. a killed benchmark takes its jobs with it ---------------------------------------------------------------

def test_sigkill_of_side_by_side_jobs_parent_ends_them(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import os, sys, time
        from pathlib import Path
        from pobax.eval._parallel import Job, run_side_by_side

        def sleeper(path):
            Path(path).write_text(str(os.getpid()))
            time.sleep(120)

        if __name__ == "__main__":
            here = Path(r"{tmp_path}")
            jobs = [Job(f"j{{k}}", sleeper, (here / f"pid{{k}}",), here / f"j{{k}}.log") for k in range(2)]
            run_side_by_side(jobs, [{{}}, {{}}], progress=False)
    """))
    parent = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    pids = [tmp_path / f"pid{k}" for k in range(2)]
    deadline = time.monotonic() + 60
    while not all(p.exists() and p.read_text() for p in pids):
        if parent.poll() is not None or time.monotonic() > deadline:
            parent.kill()
            pytest.fail("the jobs did not start: " + " ".join(p.read_text() for p in tmp_path.glob("*.log")))
        time.sleep(0.1)
    children = [int(p.read_text()) for p in pids]
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [c for c in children if _alive(c)]
    for c in alive:  # (on failure: do not leave them sleeping)
        os.kill(c, signal.SIGKILL)
    assert not alive


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"  # a zombie has ended (its reaper, the killed parent, is gone)


# --- 7. the smaller promises ------------------------------------------------------------------------------------

@pytest.fixture
def user_cells(tmp_path, monkeypatch):
    (tmp_path / "cells.py").write_text(textwrap.dedent("""
        import equinox as eqx, jax.numpy as jnp
        from pobax.memory import AbstractMemory, Dense

        class Wide(AbstractMemory):
            proj: Dense
            in_size: int = eqx.field(static=True)
            out_size: int = eqx.field(static=True)

            def __init__(self, in_size, hidden_size, *, key):
                self.in_size, self.out_size = in_size, hidden_size
                self.proj = Dense(in_size, hidden_size + 3, key=key)  # three more outputs than it declares

            def init_carry(self):
                return jnp.zeros(self.out_size)

            def __call__(self, carry, xs, starts):
                return carry, jnp.tanh(self.proj(xs))

        class Buggy(Wide):
            def __call__(self, carry, xs, starts):
                raise ValueError("a bug inside the cell")

        class NaN(Wide):  # the shapes it declares, and NaN outputs: every run diverges
            def __call__(self, carry, xs, starts):
                return carry, self.proj(xs)[:, : self.out_size] * jnp.nan
    """))
    (tmp_path / "quitter.py").write_text("import sys\nsys.exit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_user_cells_that_misbehave(user_cells, capsys):
    out = user_cells / "r"
    refused(capsys, ["train", *TINY, "--memory", "cells:Wide", "--out", out],
            "Wide(in_size=4, hidden_size=8) returns outputs of shape (4, 11)", "(time, out_size) = (4, 8)",
            "check_memory")
    refused(capsys, ["train", *TINY, "--memory", "quitter:Cell", "--out", out], "called sys.exit(0)")
    with pytest.raises(ValueError, match="a bug inside the cell"):  # the cell's own error keeps its traceback
        cli.main(["train", *TINY, "--memory", "cells:Buggy", "--out", str(out)])
    assert not out.exists()


class BrokenStep(AbstractWrapper):
    """An environment whose step has a bug: training fails as its first program compiles."""

    env: object

    def reset(self, *, key):
        return self.env.reset(key=key)

    def step(self, state, action, *, key):
        raise RuntimeError("a bug in the environment's step")


def test_a_failure_before_the_first_chunk_leaves_no_run_directory(tmp_path):
    created = []
    with pytest.raises(RuntimeError, match="a bug in the environment's step"):
        train(CFG, tmp_path / "r", progress=False, env=BrokenStep(make(CFG.env, CFG.observability)),
              on_start=created.append)
    assert created == [tmp_path / "r"] and not (tmp_path / "r").exists()  # created, then removed


def test_a_failed_write_says_how_to_resume(tmp_path, stopped, capsys):
    """A write that fails while training (a full disk; here a directory in the way of the next chunk's metrics
    file) names the error, the last checkpoint and how to continue once it is fixed."""
    run = copy(stopped, tmp_path / "my run")  # a path with a space: quoted in the command to paste
    (run / "metrics" / "00003.csv").mkdir()  # the stopped run has done chunks 0, 1 and 2
    refused(capsys, ["train", "--resume", run], f"Is a directory ({run / 'metrics' / '00003.csv'})",
            f"the last checkpoint is in {run}: fix that, then continue with pobax train --resume '{run}'",
            started=True)
    assert json.loads((run / "checkpoint.json").read_text())["chunks_done"] == 3  # as it was


def test_preset_directory_sweep_advice_and_sweep_ctrl_c(tmp_path, user_cells, capsys):
    refused(capsys, ["train", *TINY, "--preset", ".", "--out", tmp_path / "r"], "--preset '.' is a directory")
    nan = ["sweep", *TINY, "--memory", "cells:NaN", "--lr", "1e-3", "2e-3"]  # every run diverges
    refused(capsys, [*nan, "--out", tmp_path / "s"], "Every run of the sweep", "diverged", "--lr")

    def ctrl_c(chunk):
        raise KeyboardInterrupt

    # (the same sweep again: its program is compiled already)
    err = refused(capsys, [*nan, "--out", tmp_path / "s2"], "the same sweep command with the same --out continues",
                  code=130, on_chunk=ctrl_c)
    assert "--resume" not in err and not (tmp_path / "s2" / "base" / "summary.json").exists()


def test_plot_and_load_run_refuse_damaged_metrics(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "metrics.csv").write_text("garbage\n1\n")
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], "metrics.csv' is not a metrics table pobax wrote")
    with pytest.raises(ValueError, match="metrics.csv' is not a metrics table"):
        load_run(run)
    assert not (tmp_path / "c.png").exists()


@pytest.mark.parametrize("damage, message", [
    (lambda t: "".join(t.splitlines(True)[:2]), "metrics/00001.csv' is damaged"),  # cut at a line: one run's row
    (lambda t: t.replace("\n0,0,1,1024,", "\n0,0,1,1024,9", 1), "metrics/00001.csv' is damaged"),  # a number edited
    (None, "missing metrics/00001.csv"),
])
def test_plot_and_eval_of_an_unfinished_run_refuse_its_damaged_chunks(tmp_path, stopped, capsys, damage, message):
    """An interrupted run's chunk metrics cut at a line, edited or gone: plot drew the curves of what was left (eval
    refused, as a resume does); both check them against the SHA-256 hashes checkpoint.json recorded, as a resume
    does, and refuse naming the file."""
    run = copy(stopped, tmp_path / "r")
    chunk = run / "metrics" / "00001.csv"
    chunk.write_text(damage(chunk.read_text())) if damage else chunk.unlink()
    before = digest(run)
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], message)
    refused(capsys, ["eval", run, "--episodes", "2"], message)
    assert digest(run) == before and not (tmp_path / "c.png").exists()


def test_a_truncated_model_or_normaliser_is_refused_by_eval_and_render(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "model.eqx").write_bytes((run / "model.eqx").read_bytes()[:1000])
    refused(capsys, ["eval", run], "model.eqx' is damaged or does not match the run's configuration")
    refused(capsys, ["render", run, "--out", tmp_path / "e.gif"], "model.eqx' is damaged")
    normed = tmp_path / "n"
    train(dataclasses.replace(CFG, normalize_obs=True, num_seeds=1), normed, progress=False)
    (normed / "obs_norm.eqx").write_bytes((normed / "obs_norm.eqx").read_bytes()[:10])  # was a traceback
    refused(capsys, ["eval", normed], "obs_norm.eqx' is damaged or does not match the run's configuration")
    assert not (tmp_path / "e.gif").exists()
    (run / "model.eqx").unlink()  # a finished run keeps no checkpoint: was "continue it with pobax train --resume"
    refused(capsys, ["eval", run], "is a finished run without its model.eqx", "train it again into a new --out")


def test_eval_out_an_existing_file_is_refused_naming_it(tmp_path, finished, capsys):
    """`eval --out` is a directory for the eval files: an existing file there (or above it) was an `[Errno 17] File
    exists` line that named neither the flag nor the fix; the file is left as it was."""
    taken = tmp_path / "eval.json"
    taken.write_text("mine\n")
    before = digest(finished)
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", taken], f"--out {str(taken)!r} is a file",
            "pass another --out", "or remove the file")
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", taken / "sub"], f"{str(taken)!r} is a file")
    assert taken.read_text() == "mine\n" and digest(finished) == before


def test_eval_does_not_write_over_an_evaluation_of_other_settings(tmp_path, finished, capsys):
    """A second `eval` of other settings into the same directory replaced the first's files (their names hold the
    observability, the policy and the seed, not the episodes): 100 episodes' results lost to 2. Now refused by name
    before anything is played; the same settings play the same episodes and write them again."""
    out = tmp_path / "ev"
    cli.main(["eval", str(finished), "--episodes", "3", "--out", str(out)])
    first, _ = digest(out), capsys.readouterr()
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", out], "eval-partial-stochastic-seed0.json",
            "other settings (episodes 3 (now 2))", "pass another --out (or --seed)")
    refused(capsys, ["eval", finished, "--episodes", "3", "--max-steps", "5", "--out", out], "max_steps")
    assert digest(out) == first
    cli.main(["eval", str(finished), "--episodes", "3", "--out", str(out)])
    cli.main(["eval", str(finished), "--episodes", "2", "--seed", "1", "--out", str(out)])
    assert digest(out).items() >= first.items() and len([f for f in digest(out) if not f.startswith(".")]) == 4
    (out / "eval-partial-greedy-seed0.json").write_text("mine\n")
    capsys.readouterr()
    refused(capsys, ["eval", finished, "--episodes", "3", "--greedy", "--out", out], "is not an evaluation eval wrote")
    assert (out / "eval-partial-greedy-seed0.json").read_text() == "mine\n"


def test_eval_does_not_write_over_another_runs_evaluation(tmp_path, stopped, finished, capsys, monkeypatch):
    """Another run's evaluation of the same settings in one --out was written over (the run was not compared); and an
    evaluation written by another process while this one played is checked again before writing."""
    out = tmp_path / "ev"
    cli.main(["eval", str(finished), "--episodes", "2", "--out", str(out)])
    first, _ = digest(out), capsys.readouterr()
    other = copy(finished, tmp_path / "other")
    refused(capsys, ["eval", other, "--episodes", "2", "--out", out], "other settings (run_dir")
    assert digest(out) == first
    import pobax.eval._evaluate as ev

    summary = ev._summary
    theirs = tmp_path / "ev2"

    def meanwhile(run, *args):  # another eval, of other settings, finishes into the same --out while this one plays
        monkeypatch.setattr(ev, "_summary", summary)
        cli.main(["eval", str(finished), "--episodes", "3", "--out", str(theirs)])
        return summary(run, *args)

    monkeypatch.setattr(ev, "_summary", meanwhile)
    with pytest.raises(ev.EvalError, match="other settings"):
        ev.evaluate(finished, episodes=2, out=theirs)
    assert json.loads((theirs / "eval-partial-stochastic-seed0.json").read_text())["episodes"] == 3


def test_plot_and_render_refuse_outputs_they_cannot_or_must_not_write(tmp_path, finished, capsys):
    """An --out suffix matplotlib or the frame grid cannot write was a ValueError or KeyError traceback; a --json
    naming a file that is not plot's own curves (here the run's summary.json) was written over."""
    refused(capsys, ["plot", finished, "--out", tmp_path / "curves.txt"], "matplotlib cannot write '.txt' figures",
            ".png")
    refused(capsys, ["render", "--env", "halfcheetah_pixels", "--steps", "2", "--out", tmp_path / "f.bad"],
            "one PNG grid; name a .png")
    assert not list(tmp_path.iterdir())
    run = copy(finished, tmp_path / "r")
    before = digest(run)
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png", "--json", run / "summary.json"],
            "summary.json' exists and is not curves plot wrote")  # was written over with the curves
    assert digest(run) == before and not (tmp_path / "c.png").exists()
    cli.main(["plot", str(run), "--out", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")])
    cli.main(["plot", str(run), "--out", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")])  # its own


@pytest.mark.parametrize("args", [["train", "--help"], ["envs"]])
def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path, args):
    """`pobax train --help | head -1`: the reader closes the pipe before the command has written; tyro's help was a
    BrokenPipeError traceback, a command's output an `[Errno 32] Broken pipe` error and an 'Exception ignored' note.
    Now nothing is said, as for any command whose reader has gone (exit 1, as Python's recipe)."""
    p = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), *args], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, cwd=tmp_path, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    p.stdout.close()  # before it has written anything (it imports JAX first)
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 1 and err == "", err


def test_plot_best_selects_from_the_metrics_not_an_edited_summary(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "summary.json").write_text('{"x": 1}')  # valid JSON of another shape: was a KeyError traceback
    cli.main(["plot", str(run), "--best", "--out", str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").stat().st_size > 0


@pytest.mark.parametrize("text", ["[1]", '{"best_by_auc": null}', '{"best_by_auc": 99}'])
def test_eval_and_render_refuse_a_summary_json_of_another_shape(tmp_path, finished, capsys, text):
    """A finished run's summary.json edited into valid JSON of another shape: eval and render ended in an
    AttributeError or TypeError traceback, or eval wrote "best_by_auc": 99 (a set the run does not have) into its
    results; load_run, which both read it through, refuses it naming the file."""
    run = copy(finished, tmp_path / "r")
    (run / "summary.json").write_text(text)
    before = digest(run)
    message = f"{str(run / 'summary.json')!r} is not a summary pobax wrote"
    refused(capsys, ["eval", run, "--episodes", "2"], message)
    refused(capsys, ["render", run, "--out", tmp_path / "e.gif"], message)
    with pytest.raises(ValueError, match="is not a summary pobax wrote"):
        load_run(run)
    assert digest(run) == before and not (tmp_path / "e.gif").exists()


def test_a_nan_model_is_refused_by_load_run_and_eval(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    model = load_run(run).model
    nan = jax.tree.map(lambda x: jnp.full_like(x, jnp.nan) if eqx.is_inexact_array(x) else x, model)
    eqx.tree_serialise_leaves(run / "model.eqx", nan)
    before = digest(run)
    with pytest.raises(ValueError, match="non-finite parameters for run 0"):
        load_run(run)
    refused(capsys, ["eval", run, "--episodes", "2"], "non-finite parameters", "whose training did not diverge")
    assert digest(run) == before  # nothing written into the run


def test_results_shows_diverged_and_damaged_runs(tmp_path, stopped, finished, capsys):
    root = tmp_path / "runs"
    root.mkdir()
    diverged, short = copy(finished, root / "a-diverged"), copy(finished, root / "d-no-episode")
    for run, seeds_diverged in ((diverged, CFG.num_seeds), (short, 0)):  # no return: every seed diverged, or
        summary = json.loads((run / "summary.json").read_text())        # no episode ended in the last updates
        for s in summary["sets"]:
            s["disc_return"].update(mean=float("nan"), ci_low=float("nan"), ci_high=float("nan"))
            s["diverged"] = seeds_diverged
        (run / "summary.json").write_text(json.dumps(summary))
    damaged = copy(stopped, root / "b-damaged")
    (damaged / "metrics" / "00000.csv").write_text("")
    copy(stopped, root / "c-resumable")
    cli.main(["results", "--root", str(root)])
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    assert " diverged " in rows[str(diverged)] and "nan" not in rows[str(diverged)]
    assert rows[str(short)].endswith(" finished       no episode ended"), rows[str(short)]  # (was "diverged")
    assert " damaged " in rows[str(damaged)] and " resumable " in rows[str(root / "c-resumable")]


def test_results_lists_a_run_whose_summary_json_cannot_be_read_beside_the_others(tmp_path, finished, capsys):
    root = tmp_path / "runs"
    root.mkdir()
    copy(finished, root / "a")
    bad = copy(finished, root / "b")
    (bad / "summary.json").unlink()
    (bad / "summary.json").mkdir()  # was "[Errno 21] Is a directory", and no run listed
    cli.main(["results", "--root", str(root)])
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    assert " finished " in rows[str(root / "a")] and " damaged " in rows[str(bad)], rows


@pytest.mark.parametrize("cut", [lambda t: t[:-30], lambda t: "".join(t.splitlines(True)[:9]), lambda t: "garbage\n"])
def test_results_lists_a_finished_run_whose_metrics_csv_is_damaged_as_damaged(tmp_path, finished, capsys, cut):
    """A finished run's metrics.csv cut short or overwritten: `results` listed it as finished from its summary.json
    alone; it lists it as damaged and names the file, and lists the other runs as before."""
    root = tmp_path / "runs"
    root.mkdir()
    damaged, good = copy(finished, root / "a-damaged"), copy(finished, root / "b-finished")
    (damaged / "metrics.csv").write_text(cut((damaged / "metrics.csv").read_text()))
    before = digest(root)
    cli.main(["results", "--root", str(root)])
    out, err = capsys.readouterr()
    rows = {line.split()[0]: line for line in out.splitlines()[1:]}
    assert " damaged " in rows[str(damaged)] and " finished " in rows[str(good)], out
    assert err.count("\n") == 1 and f"{str(damaged / 'metrics.csv')!r}" in err and "Traceback" not in err, err
    assert digest(root) == before


@pytest.mark.parametrize("field, value", [("memory", 5), ("env", [1, 2]), ("num_seeds", "x"), ("observability", None)])
def test_results_lists_a_run_whose_config_json_was_edited_as_damaged(tmp_path, finished, capsys, field, value):
    """A field of config.json edited to a value of another type: `results` stopped on it with a TypeError or
    ValueError traceback, listing no run at all; it lists it as damaged, naming the file, beside the others."""
    root = tmp_path / "runs"
    root.mkdir()
    damaged, good = copy(finished, root / "a-edited"), copy(finished, root / "b-finished")
    record = json.loads((damaged / "config.json").read_text())
    record["config"][field] = value
    (damaged / "config.json").write_text(json.dumps(record))
    cli.main(["results", "--root", str(root)])
    out, err = capsys.readouterr()
    rows = {line.split()[0]: line for line in out.splitlines()[1:]}
    assert " damaged " in rows[str(damaged)] and " finished " in rows[str(good)], out
    assert err.count("\n") == 1 and f"{str(damaged / 'config.json')!r}" in err and "Traceback" not in err, err


@pytest.mark.parametrize("args, message", [
    (["--env", "halfcheetah_pixels", "--steps", "100000000000"], "--steps 100,000,000,000: a grid of random frames"),
    (["--env", "Navix-DMLab-Maze-01-v0", "--steps", "1025"], "holds at most 1,024"),
    (["--env", "halfcheetah_pixels", "--cols", "0"], "--cols must be an integer in [1, 1,024], got 0"),
])
def test_render_of_too_many_random_frames_is_refused(tmp_path, capsys, args, message):
    refused(capsys, ["render", *args, "--out", tmp_path / "f.png"], message)  # was an OverflowError traceback
    assert not (tmp_path / "f.png").exists()


def test_a_random_rollout_longer_than_int32_is_refused_from_python():
    from pobax.env._base import random_rollout

    with pytest.raises(ValueError, match="num_steps must be an integer in"):
        random_rollout(make("tmaze_5"), 2**31, jax.random.key(0), lambda state, obs: obs)


def test_render_draws_a_maze_under_random_actions(tmp_path, capsys):
    out = tmp_path / "maze.png"
    cli.main(["render", "--env", "Navix-DMLab-Maze-01-v0", "--steps", "3", "--out", str(out)])
    from PIL import Image

    image = np.asarray(Image.open(out).convert("RGB"))
    colours = {tuple(c) for c in image.reshape(-1, 3)[:: 7]}
    assert image.shape[1] > 3 * 100 and len(colours) >= 4  # three frames of walls, floor, goal and agent


def test_out_of_device_memory_is_one_line_and_other_runtime_errors_keep_their_traceback(tmp_path, monkeypatch,
                                                                                        capsys):
    # XLA's own out-of-memory error, raised where training runs (past the memory bound, which is a lower bound).
    def out_of_memory(*args, **kwargs):
        jnp.zeros(2**40, jnp.float32).block_until_ready()  # 4 TiB

    monkeypatch.setattr(cli, "run_train", out_of_memory)
    refused(capsys, ["train", *TINY, "--out", tmp_path / "r"], "out of device memory (RESOURCE_EXHAUSTED",
            "lower --num-envs")

    def bug(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(cli, "run_train", bug)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["train", *TINY, "--out", str(tmp_path / "r2")])


def test_a_reader_never_mistakes_a_checkpoint_being_replaced_for_a_damaged_one(tmp_path):
    """`eval`, `plot` or `results` of a run that another process trains: the trainer writes the next checkpoint,
    replaces checkpoint.json and deletes the previous checkpoint while a reader reads them, and the reader said the
    run was damaged ("missing or corrupted ... start a new run"). A manifest that changed while it was read is read
    again; one that did not change is damage, as before."""
    rd = RunDir(tmp_path / "run")
    (rd.path / "metrics").mkdir(parents=True)
    state = {"w": np.arange(20_000, dtype=np.float32)}
    chunk = pd.DataFrame({"update": [0], "return": [1.0]})

    def write(k):
        rd.write_chunk(k - 1, chunk)
        rd.save_checkpoint({"w": state["w"] + k}, chunks_done=k, num_chunks=10**6, config={})

    write(1)
    stop, errors = threading.Event(), []

    def trainer():
        k = 1
        while not stop.is_set():
            k += 1
            write(k)
            time.sleep(0.002)  # a trainer's chunks are seconds apart; a reader is never starved for 20 of them

    t = threading.Thread(target=trainer)
    t.start()
    try:
        reads = 0
        deadline = time.time() + 3.0
        while time.time() < deadline:
            try:
                rd.checkpoint_bytes()
                reads += 1
            except CheckpointError as e:
                errors.append(str(e))
    finally:
        stop.set()
        t.join()
    assert not errors, errors[:2]
    assert reads > 10
    (rd.path / rd.manifest()["file"]).write_bytes(b"damaged")  # no writer: damage is still damage
    with pytest.raises(CheckpointError, match="missing or corrupted"):
        rd.checkpoint_bytes()


def test_a_run_that_finishes_while_it_is_read_is_read_finished(tmp_path, stopped, finished, monkeypatch):
    """The trainer's last chunk: metrics.csv, model.eqx and summary.json written, then the checkpoint cleared. A reader
    (`eval`, `results`) that found no model.eqx and went for the checkpoint found it gone and called the run damaged;
    it is read again, finished."""
    read = RunDir.checkpoint_bytes

    def finishing(self):  # the trainer finishes between the reader's look and its read
        for name in ("metrics.csv", "model.eqx", "summary.json"):
            (self.path / name).write_bytes((finished / name).read_bytes())
        self.clear_checkpoint()
        return read(self)

    monkeypatch.setattr(RunDir, "checkpoint_bytes", finishing)
    loaded = load_run(copy(stopped, tmp_path / "loaded"))
    assert loaded.finished and loaded.source == "model.eqx"
    [row] = list_runs(copy(stopped, tmp_path / "listed"))
    assert row["state"] == "finished" and row["disc_return"] is not None, row
