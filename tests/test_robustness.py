"""A result is either right or refused: bad input is one line and exit 2, before anything is compiled or written;
nothing already written changes; diverged runs are counted, never averaged in; Ctrl-C says how to resume.
(Checkpoints stopped at every write step, and corrupted or mismatched ones: tests/test_resume.py.)"""

import hashlib
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import cli
import pobax.agent._train as T
import pobax.env as E
from pobax.agent import TrainConfig
from pobax.eval import summarize, train

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--env", "tmaze_3", "--memory", "memoryless", "--hidden-size", "8", "--num-envs", "2", "--num-minibatches",
        "2", "--num-steps", "16", "--total-steps", "96", "--num-seeds", "2", "--num-chunks", "3", "--quiet"]
GAP = [a for a in TINY if a not in ("--memory", "memoryless")]  # gap sets the memory per agent
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
def test_preset_files_are_validated_like_the_command_line(tmp_path, preset, message):
    (tmp_path / "p.json").write_text(json.dumps({"preset": preset}))
    proc = pobax("train", *TINY, "--preset", tmp_path / "p.json", "--out", tmp_path / "run", cwd=tmp_path)
    refused(proc, message)
    assert "p.json" in proc.stderr or "--lr values" in message  # the file is named where the type is wrong
    assert not (tmp_path / "run").exists()


def test_wrong_inputs_change_nothing_already_written(tmp_path, stopped):
    before = digest(stopped)
    (tmp_path / "afile").write_text("x")
    cases = [
        (("train", *TINY, "--out", stopped), "already exists and is not empty"),  # never overwrite
        (("train", "--resume", stopped, "--lr", "1e-3"), "drop --lr"),  # --resume ignores no flag silently
        (("train", "--resume", stopped, "--preset", "paper"), "drop --preset"),
        (("train", *TINY, "--max-chunks", "0", "--out", tmp_path / "r0"), "--max-chunks must be a positive"),
        (("train", *TINY, "--out", tmp_path / "afile"), "is a file"),
        (("train", "--env", "rocksample_7_8", "--memory", "gru", "--preset", "paper", "--out", tmp_path / "r1"),
         "no hyperparameters for rocksample_7_8"),
        (("sweep", *TINY, "--lr", "1e-3", "1e-4", "--out", stopped), "holds files this command did not write"),
        (("gap", *GAP, "--out", stopped), "holds files this command did not write"),
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


def test_broken_config_json_names_the_file(tmp_path, stopped):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{not json")
    refused(pobax("train", "--resume", run, cwd=tmp_path), "config.json")


def test_a_second_sweep_into_the_same_folder_is_refused(tmp_path):
    out = tmp_path / "sweep"
    assert pobax("sweep", *TINY, "--lr", "1e-3", "1e-4", "--out", out, cwd=tmp_path).returncode == 0
    before = digest(out)
    refused(pobax("sweep", *TINY, "--lr", "1e-3", "1e-4", "--out", out, cwd=tmp_path), "another call's results")
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


def test_ctrl_c_names_the_run_and_how_to_resume(tmp_path, monkeypatch, capsys):
    real = T.Runs.chunks

    def interrupted(self, state, first=0, last=None):
        for chunk in real(self, state, first, last):
            yield chunk
            raise KeyboardInterrupt

    monkeypatch.setattr(T.Runs, "chunks", interrupted)
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        cli.main(["train", *TINY[:-1], "--out", str(run)])
    assert e.value.code == 130
    out, err = capsys.readouterr()
    assert f"run directory: {run}" in out  # named at the start
    last = err.strip().splitlines()[-1]  # after the progress lines: one line that says how to resume
    assert last.startswith("error: interrupted") and f"pobax train --resume {run}" in last and "Traceback" not in err
    monkeypatch.undo()
    cli.main(["train", "--resume", str(run), "--quiet"])
    assert (run / "summary.json").exists()


def test_result_files_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        run = train(CFG, tmp_path / "run", progress=False).run_dir
    finally:
        os.umask(old)
    for name in ("config.json", "metrics.csv", "summary.json", "model.eqx", "metrics/00000.csv"):
        assert stat.S_IMODE((run / name).stat().st_mode) == 0o644, name


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_directories_are_refused_before_compiling(tmp_path, stopped):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    refused(pobax("train", *TINY, "--out", ro / "run", cwd=tmp_path), "Cannot write the run directory")
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-r", str(stopped), str(copy)], check=True)
    copy.chmod(0o555)
    refused(pobax("train", "--resume", copy, cwd=tmp_path), "Cannot write the run directory")


class NaNReward(E.AbstractWrapper):
    """T-Maze whose rewards are NaN: every loss is NaN, so every run diverges."""

    env: object

    def reset(self, *, key):
        return self.env.reset(key=key)

    def step(self, state, action, *, key):
        s, ts = self.env.step(state, action, key=key)
        return s, eqx.tree_at(lambda t: t.reward, ts, ts.reward * jnp.nan)


def test_diverged_runs_are_counted_not_averaged(monkeypatch, capsys):
    real = T.make
    monkeypatch.setattr(T, "make", lambda *a, **k: NaNReward(real(*a, **k)))
    r = train(CFG, save=False, progress=False)
    s = r.summary["sets"][0]
    assert s["diverged"] == 2 and s["diverged_seeds"] == [0, 1] and r.summary["diverged_runs"] == 2
    assert np.isnan(s["disc_return"]["mean"]) and s["disc_return"]["per_seed"] == []
    assert (r.metrics["nonfinite"] > 0).all()


def test_diverged_sets_lose_the_selection():
    rows = []
    for h, (lr, nonfinite) in enumerate([(1e-3, 0.0), (0.5, 1.0)]):
        for seed in range(2):
            for u in range(10):
                # set 1 would win by return, but one of its seeds diverged
                rows.append(dict(hp_index=h, seed=seed, update=u, lr=lr, disc_return=float(h + 1), **{
                    "return": float(h + 1), "nonfinite": nonfinite if (seed == 1 and u > 5) else 0.0}))
    cfg = TrainConfig(lr=(1e-3, 0.5), num_seeds=2)
    summary = summarize(cfg, pd.DataFrame(rows))
    assert summary["best_by_auc"] == 0 and not summary["all_sets_diverged"]
    bad = summary["sets"][1]
    assert bad["diverged"] == 1 and bad["disc_return"]["per_seed"] == [2.0]  # seed 1 left out, not averaged in
