"""A result is either right or refused: bad input is one line and exit 2, before anything is compiled or written;
nothing already written changes; diverged runs are counted, never averaged in; Ctrl-C says how to resume.
(Checkpoints stopped at every write step, and corrupted or mismatched ones: tests/test_resume.py.)"""

import dataclasses
import hashlib
import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import cli
from _hostile import refused as refused_here  # (`refused` in this process: no start-up cost)
from pobax.agent import TrainConfig
from pobax.eval import Interrupted, summarize, train

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--env", "tmaze_3", "--memory", "memoryless", "--hidden-size", "8", "--num-envs", "2", "--num-minibatches",
        "2", "--num-steps", "16", "--total-steps", "96", "--num-seeds", "2", "--num-chunks", "3", "--quiet"]
GAP = [a for a in TINY if a not in ("--memory", "memoryless")] + ["--agents", "floor", "gru"]  # memory: per agent
CFG = TrainConfig(env="tmaze_3", memory="memoryless", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                  total_steps=96, num_seeds=2, num_chunks=3)


def digest(path: Path) -> dict:
    """Every file under `path` with its content hash (and mode)."""
    return {str(p.relative_to(path)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mode)
            for p in sorted(path.rglob("*")) if p.is_file()}


def pobax(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "cli.py"), *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600)


def refused(proc: subprocess.CompletedProcess, message: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.strip().count("\n") == 0, proc.stderr
    assert proc.stdout == "", proc.stdout  # the one line is all: no run directory announced before a refusal


@pytest.fixture(scope="module")
def stopped(tmp_path_factory) -> Path:
    """A run stopped after its first chunk (resumable)."""
    run = tmp_path_factory.mktemp("stopped") / "run"
    train(CFG, run, progress=False, max_chunks=1)
    return run


@pytest.mark.parametrize("preset, message", [
    ({"anneal_lr": "no"}, "--anneal-lr must be true or false, got 'no'"),
    ({"lr": "fast"}, "--lr takes numbers, got 'fast'"),
    ({"lr": None}, "--lr takes numbers, got None"),
    ({"hidden_size": "big"}, "--hidden-size must be an integer, got 'big'"),
    ({"num_envs": 4.5}, "--num-envs must be an integer, got 4.5"),
    ({"lr": [2.5e-4, 1e30]}, "--lr values must be in (0.0, 1.0] and finite, got 1e+30"),
    ({"learning_rate": 1e-3}, "unknown fields: learning_rate"),
])
def test_preset_files_are_validated_like_the_command_line(tmp_path, capsys, preset, message):
    (tmp_path / "p.json").write_text(json.dumps({"preset": preset}))
    err = refused_here(capsys, ["train", *TINY, "--preset", tmp_path / "p.json", "--out", tmp_path / "run"], message)
    assert "p.json" in err or "--lr values" in message  # the file is named where the type is wrong
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_wrong_inputs_change_nothing_already_written(tmp_path, stopped):
    before = digest(stopped)
    (tmp_path / "afile").write_text("x")
    cases = [
        (("train", *TINY, "--out", stopped), f"continue it with pobax train --resume {stopped}"),  # never overwrite
        (("train", "--resume", stopped, "--lr", "1e-3"), "drop --lr"),  # --resume ignores no flag silently
        (("train", "--resume", stopped, "--preset", "paper"), "drop --preset"),
        (("train", *TINY, "--max-chunks", "0", "--out", tmp_path / "r0"), "--max-chunks must be a positive"),
        (("train", *TINY, "--out", tmp_path / "afile"), "is a file"),
        (("train", "--env", "rocksample_7_8", "--memory", "gru", "--preset", "paper", "--out", tmp_path / "r1"),
         "no hyperparameters for rocksample_7_8"),
        (("sweep", *TINY, "--lr", "1e-3", "1e-4", "--out", stopped), "holds files and no pobax-sweep.json"),
        (("gap", *GAP, "--out", stopped), "holds files and no pobax-gap.json"),
        (("gap", *GAP, "--memory", "gru", "--out", tmp_path / "g"), "--memory is set per agent"),
        (("benchmark", "--envs", "tmaze_3", "--budget", "smoke", "--out", stopped), "holds other files"),
        (("benchmark", "--suite", "discrete", "--envs", "tmaze_3", "--out", tmp_path / "b"), "not both"),
        (("results", "--root", tmp_path / "missing"), "is not a directory"),
        (("plot", "--out", tmp_path / "c.png"), "at least one run directory"),
        (("plot", stopped, "--out", tmp_path / "afile" / "c.png"), "is a file, not a directory"),
    ]
    for args, message in cases:
        refused(pobax(*args, cwd=tmp_path), message)
    assert digest(stopped) == before
    assert not any((tmp_path / n).exists() for n in ("r0", "r1", "g", "b"))


def test_more_wrong_inputs_are_one_line_and_change_nothing(tmp_path, stopped, capsys):
    """Refusals before any compile, run in this process: one line on stderr, nothing on stdout, exit 2, and no file
    under the run, a folder of someone else's (with a config.json of its own) or a results folder changes."""
    foreign = tmp_path / "foreign"
    (foreign / "sub").mkdir(parents=True)
    (foreign / "config.json").write_text('{"model": "not a pobax run"}')
    nested = tmp_path / "nested"
    (nested / "sub").mkdir(parents=True)
    (nested / "sub" / "config.json").write_text("{}")
    (tmp_path / "afile").write_text("x")
    damaged = tmp_path / "bench"
    (damaged / "agents" / "tmaze_3").mkdir(parents=True)
    (damaged / "benchmark.json").write_text('{"envs": ["tmaze_3"], "calls": []}')
    (damaged / "agents" / "tmaze_3" / "floor.json").write_text('{"config": ')
    before = {p: digest(p) for p in (stopped, foreign, nested, damaged)}
    cases = [
        (("train", "--resume", stopped, "--out", tmp_path / "x"), "drop --out"),
        (("train", *TINY, "--memory", "trxl", "--gating-bias", "inf", "--out", tmp_path / "r"),
         "--gating-bias must be a finite number"),
        (("train", *TINY, "--lr", "1.5", "--out", tmp_path / "r"), "--lr values must be in (0.0, 1.0]"),
        (("train", *TINY, "--max-chunks", "-1", "--out", tmp_path / "r"), "--max-chunks must be a positive"),
        (("train", *TINY, "--out", foreign), "holds a config.json that is not a pobax run's"),
        (("train", *TINY, "--out", nested), "already exists and is not empty"),
        (("sweep", *TINY, "--lr", "1e-3", "1e-4", "--resume", stopped), "sweep does not take --resume"),
        (("plot", stopped, "--out", tmp_path / "figure"), "neither a directory nor an image name"),
        (("results", "--root", tmp_path / "afile"), "is not a directory"),
        (("benchmark", "--envs", "tmaze_3", "--budget", "smoke", "--agents", "floor", "--out", damaged),
         "floor.json' is not valid JSON"),
    ]
    for args, message in cases:
        refused_here(capsys, args, message)
    assert {p: digest(p) for p in before} == before
    assert not (tmp_path / "r").exists() and not (tmp_path / "figure.png").exists()


def test_a_mixed_or_corrupted_checkpoint_is_refused_before_anything_runs(tmp_path, stopped, capsys):
    """The issue's reproduction: a state newer than the chunk count beside it (here: the older checkpoint.json put
    back after another chunk), then a flipped byte inside the state. `--resume` refuses both, printing one line."""
    run = tmp_path / "run"
    subprocess.run(["cp", "-r", str(stopped), str(run)], check=True)
    old_manifest = (run / "checkpoint.json").read_text()
    train(CFG, run, progress=False, resume=True, max_chunks=1)
    (run / "checkpoint.json").write_text(old_manifest)
    before = digest(run)
    refused_here(capsys, ["train", "--resume", run], "is missing or corrupted (its SHA-256 does not match")
    assert digest(run) == before
    subprocess.run(["rm", "-r", str(run)], check=True)
    subprocess.run(["cp", "-r", str(stopped), str(run)], check=True)
    state = run / json.loads(old_manifest)["file"]
    data = bytearray(state.read_bytes())
    data[len(data) // 2] ^= 0xFF
    state.write_bytes(bytes(data))
    before = digest(run)
    refused_here(capsys, ["train", "--resume", run], "is missing or corrupted")
    assert digest(run) == before


def test_results_lists_damaged_runs_beside_the_others(tmp_path, stopped, capsys):
    root = tmp_path / "runs"
    root.mkdir()
    for name in ("a", "b"):
        subprocess.run(["cp", "-r", str(stopped), str(root / name)], check=True)
    (root / "a" / "summary.json").write_text("{")  # damaged
    (root / "other").mkdir()
    (root / "other" / "config.json").write_text("[1, 2]")  # another program's: not a run
    cli.main(["results", "--root", str(root)])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines()[1:] if line.strip()]
    assert len(rows) == 2 and "damaged" in rows[0] and "resumable" in rows[1], out


def test_a_run_killed_in_its_first_write_can_be_run_again(tmp_path, stopped):
    """A kill in the middle of writing config.json leaves only a temporary file: the same --out takes the run."""
    run = tmp_path / "run"
    (run / "metrics").mkdir(parents=True)
    (run / ".config.json.1a2b3c.tmp").write_text('{"config": {"en')
    (run / "metrics" / ".00000.csv.4d5e6f.tmp").write_text("hp_index,se")
    train(CFG, run, progress=False, max_chunks=1)
    assert not list(run.rglob(".*.tmp"))
    assert (run / "metrics" / "00000.csv").read_bytes() == (stopped / "metrics" / "00000.csv").read_bytes()


def test_broken_config_json_names_the_file(tmp_path, stopped):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{not json")
    refused(pobax("train", "--resume", run, cwd=tmp_path), "config.json")


@pytest.mark.slow
def test_a_sweep_continues_where_it_stopped_and_refuses_another_grid(tmp_path):
    import pobax.eval._sweep as S

    cfg, axes = dataclasses.replace(CFG, lr=(1e-3, 1e-4)), {"hidden_size": [8, 16]}
    whole = S.sweep(cfg, tmp_path / "whole", axes=axes, progress=False)
    programs = 0

    def stopped_in_the_second_program(chunk):  # Ctrl-C after the second program's first chunk
        nonlocal programs
        programs += chunk.index == 0
        if programs == 2:
            raise KeyboardInterrupt

    out = tmp_path / "sweep"
    with pytest.raises(KeyboardInterrupt):
        S.sweep(cfg, out, axes=axes, progress=False, on_chunk=stopped_in_the_second_program)
    first, second = out / "hidden_size=8", out / "hidden_size=16"
    assert (first / "summary.json").exists() and not (second / "summary.json").exists()
    assert json.loads((second / "checkpoint.json").read_text())["chunks_done"] == 1
    finished = digest(first)
    report = S.sweep(cfg, out, axes=axes, progress=False)
    assert digest(first) == finished  # reused, not trained again
    assert [p["summary"]["sets"] for p in report["programs"]] == [p["summary"]["sets"] for p in whole["programs"]]
    assert report["best"]["hyperparameters"] == whole["best"]["hyperparameters"]
    before = digest(out)
    refused(pobax("sweep", *TINY, "--lr", "1e-3", "1e-5", "--axis", "hidden_size=8,16", "--out", out, cwd=tmp_path),
            "another call's results")
    assert digest(out) == before


def test_a_run_killed_before_its_first_checkpoint_can_be_resumed_or_rerun(tmp_path):
    run = tmp_path / "run"
    train(CFG, run, progress=False, max_chunks=1)
    for p in [*run.glob("checkpoint*"), *run.glob("metrics/*")]:  # as if killed before the first checkpoint
        p.unlink()
    resumed = train(CFG, run, progress=False, resume=True)
    assert resumed.summary["finished"]
    for p in [p for p in run.rglob("*") if p.is_file() and p.name != "config.json"]:
        p.unlink()
    again = train(CFG, run, progress=False)  # the same --out again: nothing in it to lose
    assert (run / "metrics.csv").read_bytes() == again.run_dir.joinpath("metrics.csv").read_bytes()
    pd.testing.assert_frame_equal(resumed.metrics, again.metrics)


def test_stray_temporary_files_are_removed_on_resume(tmp_path):
    run = tmp_path / "run"
    train(CFG, run, progress=False, max_chunks=1)
    (run / ".checkpoint-00002.eqx.abc.tmp").write_bytes(b"half a state")  # a SIGKILL in the middle of a write
    train(CFG, run, progress=False, resume=True)
    assert not list(run.glob(".*.tmp"))


def interrupt(chunk):
    raise KeyboardInterrupt  # Ctrl-C after the chunk, its checkpoint written


def test_ctrl_c_names_the_run_and_how_to_resume(tmp_path, capsys):
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        cli.main(["train", *TINY[:-1], "--out", str(run)], on_chunk=interrupt)
    assert e.value.code == 130
    out, err = capsys.readouterr()
    assert f"run directory: {run}" in out  # named at the start
    last = err.strip().splitlines()[-1]  # after the progress lines: one line that says how to resume
    assert last.startswith("error: interrupted") and f"pobax train --resume {run}" in last and "Traceback" not in err
    assert f"the last checkpoint is in {run}" in last
    cli.main(["train", "--resume", str(run), "--quiet"])
    assert (run / "summary.json").exists()


def test_interrupted_before_the_first_checkpoint_says_how_to_start_again(tmp_path, capsys):
    """Ctrl-C before the first checkpoint: here after the only chunk of a run of one (the last chunk has no checkpoint:
    the results follow it). (A real Ctrl-C while the first program compiles: test_ctrl_c_in_a_real_process_...)"""
    run = tmp_path / "run"
    one_chunk = [*TINY[:-3], "--num-chunks", "1"]  # TINY's --num-chunks 3 --quiet
    with pytest.raises(SystemExit) as e:
        cli.main(["train", *one_chunk, "--out", str(run)], on_chunk=interrupt)
    out, err = capsys.readouterr()
    assert e.value.code == 130 and out == f"run directory: {run}\n"
    progress, last = err.splitlines()
    assert progress.startswith("[1/1] ")
    assert last == f"error: interrupted before the first checkpoint of {run}: start it again with pobax train " \
                   f"--resume {run}"
    assert not (run / "checkpoint.json").exists()


@pytest.fixture
def ctrl_c_default():
    """Python's own Ctrl-C handler in this process, as in a terminal: a shell without job control starts background
    commands (`pytest ... &`) with SIGINT ignored, and their subprocesses inherit that."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_dropped_ctrl_c_stops_at_the_next_chunk_boundary(tmp_path, stopped, ctrl_c_default):
    """Python drops a KeyboardInterrupt raised inside a garbage-collection callback (JAX registers one): the Ctrl-C
    still stops the run, at the end of the chunk, with its checkpoint written. Here a Ctrl-C arrives inside a
    collection started after the first chunk."""
    import gc
    import signal

    sent = []

    def ctrl_c_in_a_collection(phase, info):
        if not sent:
            sent.append(phase)
            signal.raise_signal(signal.SIGINT)  # the handler sees it inside a gc callback: nothing is raised here

    def collect(chunk):
        if chunk.index == 0:
            gc.callbacks.append(ctrl_c_in_a_collection)
            gc.collect()

    run = tmp_path / "run"
    try:
        with pytest.raises(Interrupted) as e:
            train(CFG, run, progress=False, on_chunk=collect)
    finally:
        if ctrl_c_in_a_collection in gc.callbacks:
            gc.callbacks.remove(ctrl_c_in_a_collection)
    assert sent and e.value.run_dir == run and e.value.checkpoint
    assert json.loads((run / "checkpoint.json").read_text())["chunks_done"] == 1
    assert digest(run)["metrics/00000.csv"] == digest(stopped)["metrics/00000.csv"]
    assert not (run / "metrics" / "00001.csv").exists()


@pytest.mark.slow
@pytest.mark.parametrize("signum, said", [(2, "interrupted"), (15, "terminated (SIGTERM)")])
def test_ctrl_c_or_kill_in_a_real_process_exits_with_one_line(tmp_path, ctrl_c_default, signum, said):
    """SIGINT while the first program compiles or runs: exit 130, the resume command, no traceback, and no crash of
    the interpreter torn down under XLA's threads (that was a segmentation fault, in 1 of 6 tries here). A `kill`
    (SIGTERM, a scheduler's preemption) likewise, exit 143 (it ended the process without a word)."""
    run = tmp_path / "run"
    long = [a if a != "96" else "960000" for a in TINY[:-1]]
    proc = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "train", *long, "--out", str(run)], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "JAX_PLATFORMS": "cpu"})
    first = proc.stdout.readline()
    time.sleep(2)  # into the compilation or the first chunk: XLA's threads at work
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=120)
    assert first == f"run directory: {run}\n"
    assert proc.returncode == 128 + signum, err
    assert "Traceback" not in err and "Fatal Python error" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"error: {said}") and f"pobax train --resume {run}" in last, err


@pytest.mark.slow
def test_a_kill_of_a_benchmark_with_jobs_says_how_to_continue(tmp_path):
    """SIGTERM to `benchmark --jobs 2`: its jobs ended, exit 143, and nothing on stderr (in-process, one job, it says
    how to continue); now the same line as Ctrl-C, and the same command continues."""
    out = tmp_path / "b"
    cmd = [sys.executable, str(ROOT / "cli.py"), "benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--jobs", "2",
           "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "JAX_PLATFORMS": "cpu"})
    while not (line := proc.stdout.readline()).startswith("== started"):  # (after the plan's line)
        assert line, "the benchmark ended before it started a job"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.strip().splitlines() == ["error: interrupted; the same command with the same --out continues "
                                        "(finished agents are kept, the interrupted one resumes from its last "
                                        "checkpoint): pobax " + " ".join(cmd[2:])], err


@pytest.mark.parametrize("umask", [0o027, 0o002])
def test_result_files_honour_the_umask(tmp_path, umask):
    """The umask in force when the files are written (not the one when pobax was imported)."""
    old = os.umask(umask)
    try:
        run = train(CFG, tmp_path / "run", progress=False).run_dir
    finally:
        os.umask(old)
    for name in ("config.json", "metrics.csv", "summary.json", "model.eqx", "timing.csv", "metrics/00000.csv"):
        assert stat.S_IMODE((run / name).stat().st_mode) == 0o666 & ~umask, name
    assert stat.S_IMODE(run.stat().st_mode) == 0o777 & ~umask


def _unprivileged() -> list[str] | None:
    """A command prefix under which the permission bits hold: none needed for a user; for root, setpriv without the
    capabilities that bypass them (None where that is not available)."""
    if os.geteuid() != 0:
        return []
    import tempfile

    caps = "-dac_override,-dac_read_search,-fowner"
    prefix = ["setpriv", f"--inh-caps={caps}", f"--bounding-set={caps}", "--"]
    with tempfile.TemporaryDirectory() as d:
        Path(d, "ro").mkdir(mode=0o555)
        try:
            probe = subprocess.run([*prefix, "touch", str(Path(d, "ro", "x"))], capture_output=True)
        except OSError:
            return None
        return prefix if probe.returncode != 0 and not Path(d, "ro", "x").exists() else None


@pytest.mark.slow
def test_read_only_directories_are_refused_before_compiling(tmp_path, stopped):
    prefix = _unprivileged()
    if prefix is None:
        pytest.skip("root, and no setpriv to drop the capabilities that bypass permissions")

    ro = tmp_path / "ro"
    ro.mkdir()
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-r", str(stopped), str(copy)], check=True)
    before = digest(copy)
    cases = [
        (("train", *TINY, "--out", ro / "run"), "Cannot write the run directory"),
        (("train", "--resume", copy), "Cannot write the run directory"),
        (("plot", copy, "--out", ro / "c.png"), f"cannot write in '{ro}'"),
        (("benchmark", "--envs", "tmaze_3", "--budget", "smoke", "--out", ro / "b"), "Cannot write --out"),
        (("sweep", *TINY, "--lr", "1e-3", "1e-4", "--out", ro / "s"), "Cannot write --out"),
    ]
    for d in (ro, copy, copy / "metrics"):
        d.chmod(0o555)
    try:  # the commands run side by side: each one only starts up and refuses
        procs = [subprocess.Popen([*prefix, sys.executable, str(ROOT / "cli.py"), *map(str, args)], cwd=tmp_path,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  env={**os.environ, "JAX_PLATFORMS": "cpu"}) for args, _ in cases]
        for proc, (args, message) in zip(procs, cases):
            out, err = proc.communicate(timeout=300)
            refused(subprocess.CompletedProcess(args, proc.returncode, out, err), message)
    finally:
        for d in (ro, copy, copy / "metrics"):
            d.chmod(0o755)
    assert digest(copy) == before and not any(ro.iterdir())


@pytest.mark.slow
def test_diverged_runs_are_counted_not_averaged(tmp_path, user_cells, capsys):
    """Marked in the metrics, the summary and the printed table (a user's cell that returns NaN: conftest.py's)."""
    cli.main(["train", *TINY, "--memory", "cells:NaN", "--out", str(tmp_path / "run")])
    printed = capsys.readouterr().out
    assert "(2 of 2 seeds diverged, left out)" in printed
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    s = summary["sets"][0]
    assert s["diverged"] == 2 and s["diverged_seeds"] == [0, 1] and summary["diverged_runs"] == 2
    assert s["disc_return"]["mean"] is None or np.isnan(s["disc_return"]["mean"])
    assert s["disc_return"]["per_seed"] == []
    assert (pd.read_csv(tmp_path / "run" / "metrics.csv")["nonfinite"] > 0).all()


def _two_sets() -> pd.DataFrame:
    """Metrics of two sets × two seeds: set 1 has the larger returns, but its seed 1 diverged after update 5."""
    rows = []
    for h, (lr, nonfinite) in enumerate([(1e-3, 0.0), (0.5, 1.0)]):
        for seed in range(2):
            for u in range(10):
                rows.append(dict(hp_index=h, seed=seed, update=u, env_step=64 * (u + 1), lr=lr,
                                 disc_return=float(h + 1) + 10.0 * seed, **{
                                     "return": float(h + 1), "nonfinite": nonfinite if (seed == 1 and u > 5) else 0.0}))
    return pd.DataFrame(rows)


def test_diverged_sets_lose_the_selection():
    cfg = TrainConfig(lr=(1e-3, 0.5), num_seeds=2)
    summary = summarize(cfg, _two_sets())
    assert summary["best_by_auc"] == 0 and not summary["all_sets_diverged"]
    bad = summary["sets"][1]
    assert bad["diverged"] == 1 and bad["disc_return"]["per_seed"] == [2.0]  # seed 1 left out, not averaged in


def test_a_sweep_never_selects_a_set_with_a_diverged_run():
    """Across programs too: the other program's set has the larger AUC, but one of its seeds diverged."""
    from pobax.eval import select_best

    programs, configs = [], []
    for hidden in (8, 16):
        cfg = dataclasses.replace(CFG, hidden_size=hidden)
        metrics = _two_sets()
        one = metrics[metrics.hp_index == 1].assign(hp_index=0)  # AUC 2 (seed 0; seed 1 diverged)
        if hidden == 8:  # the same curves at a quarter, and no divergence: AUC (0.5 + 3) / 2
            one = one.assign(disc_return=one.disc_return / 4, nonfinite=0.0)
        programs.append({"axis": {"hidden_size": hidden}, "run_dir": f"sweep/hidden_size={hidden}",
                         "summary": summarize(cfg, one)})
        configs.append(cfg)
    aucs = {p["axis"]["hidden_size"]: p["summary"]["sets"][0]["disc_return_auc"]["mean"] for p in programs}
    assert aucs == {8: 1.75, 16: 2.0}  # the diverged program's set has the larger AUC, and loses
    best, program = select_best(programs, configs, "sweep")
    assert best["axis"] == {"hidden_size": 8} and best["diverged"] == 0 and program.hidden_size == 8
    assert best["run_dir"] == "sweep/hidden_size=8" and best["disc_return_auc"]["mean"] == 1.75
    best, _ = select_best(programs[1:], configs[1:], "sweep")  # alone, a set with a diverged seed is selected
    assert best["axis"] == {"hidden_size": 16} and best["diverged"] == 1


def test_learning_curves_leave_diverged_runs_out():
    from pobax.eval import curve_with_ci

    metrics = _two_sets()
    _, mean, low, high = curve_with_ci(metrics, hp_index=1, points=10)  # seed 1 (returns 12) diverged
    np.testing.assert_array_equal(mean, np.full(10, 2.0))
    assert np.isnan(low).all() and np.isnan(high).all()  # one seed left: no interval
    _, mean, _, _ = curve_with_ci(metrics, hp_index=0, points=10)
    np.testing.assert_array_equal(mean, np.full(10, 6.0))  # both seeds: (1 + 11) / 2


def test_ctrl_c_inside_a_gc_callback_asks_the_loop_to_stop():
    """Python drops (and prints) an exception raised inside a garbage-collection callback: there the handler only
    sets `requested`, which the training loop reads at its next chunk boundary; elsewhere it raises at once."""
    import gc

    from pobax.eval._interrupt import _CtrlC

    ctrl_c, seen = _CtrlC(), []

    def callback(phase, info):
        if phase == "start" and not seen:
            try:
                ctrl_c._handle(2, sys._getframe())
                seen.append("asked")
            except KeyboardInterrupt:
                seen.append("raised")

    gc.callbacks.append(callback)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(callback)
    assert seen == ["asked"] and ctrl_c.requested
    with pytest.raises(KeyboardInterrupt):
        ctrl_c._handle(2, sys._getframe())
