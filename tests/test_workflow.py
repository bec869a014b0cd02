"""The experiment workflow from the CLI: presets, sweep → best.json → train, stop/resume, results, plot."""

import json

import pandas as pd
import pytest

import cli
from pobax.agent import TrainConfig, paper_preset
from pobax.eval import list_runs

TINY = ["--env", "tmaze_5", "--memory", "memoryless", "--hidden-size", "8", "--num-envs", "4", "--num-steps", "16",
        "--num-minibatches", "2", "--total-steps", str(4 * 16 * 4), "--num-chunks", "2", "--quiet"]


def test_paper_preset_and_explicit_flags(tmp_path):
    p = paper_preset("tmaze_10", "gru")
    assert p["lr"] == (2.5e-3,) and p["lambda0"] == (0.7,) and p["action_concat"] and p["hidden_size"] == 32
    assert paper_preset("tmaze_10", "memoryless", observability="full")["lambda0"] == (0.9,)  # the ceiling (ours)
    assert paper_preset("tmaze_10", "memoryless", observability="full", original=True)["lambda0"] == (0.5,)  # paper
    assert paper_preset("tmaze_10", "gru", double_critic=True)["ld_weight"] == (0.5,)
    cli.main(["train", *TINY, "--preset", "paper", "--hidden-size", "8", "--total-steps", str(4 * 16 * 4),
              "--out", str(tmp_path / "run")])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    assert cfg["lr"] == [2.5e-4] and cfg["lambda0"] == [0.3]  # T-Maze memoryless row of the paper
    assert cfg["hidden_size"] == 8 and cfg["total_steps"] == 4 * 16 * 4  # explicit flags win over the preset


@pytest.mark.slow
def test_sweep_selects_writes_preset_and_train_loads_it(tmp_path, capsys):
    out = tmp_path / "sweep"
    cli.main(["sweep", *TINY, "--lr", "2.5e-2", "2.5e-4", "--num-seeds", "2", "--axis", "hidden_size=8,16",
              "--max-runs", "2", "--out", str(out)])
    report = json.loads((out / "sweep.json").read_text())
    # 2 structural programs, each split into 2 parts of (1 lr × 2 seeds) by --max-runs 2
    assert len(report["programs"]) == 4
    aucs = [(s["disc_return_auc"]["mean"], p["axis"], s["lr"]) for p in report["programs"] for s in p["summary"]["sets"]]
    best = max(aucs, key=lambda a: a[0])
    assert report["best"]["hyperparameters"]["lr"] == best[2] and report["best"]["axis"] == best[1]
    preset = json.loads((out / "best.json").read_text())["preset"]
    assert preset["hidden_size"] == best[1]["hidden_size"] and preset["lr"] == [best[2]]
    cli.main(["train", "--preset", str(out / "best.json"), "--num-seeds", "3", "--quiet", "--out", str(tmp_path / "re")])
    cfg = json.loads((tmp_path / "re" / "config.json").read_text())["config"]
    assert cfg["lr"] == [best[2]] and cfg["hidden_size"] == best[1]["hidden_size"] and cfg["num_seeds"] == 3


@pytest.mark.slow
def test_stop_resume_results_and_plot_from_the_cli(tmp_path, capsys):
    run = tmp_path / "runs" / "a"
    cli.main(["train", *TINY, "--max-chunks", "1", "--out", str(run)])
    assert "--resume" in capsys.readouterr().out
    assert [r["state"] for r in list_runs(tmp_path / "runs")] == ["resumable"]
    cli.main(["train", "--resume", str(run), "--quiet"])
    rows = list_runs(tmp_path / "runs")
    assert rows[0]["state"] == "finished" and rows[0]["env"] == "tmaze_5"
    assert len(pd.read_csv(run / "metrics.csv")) == 4 * 5  # one row per update and run (5 seeds by default)
    cli.main(["results", "--root", str(tmp_path / "runs")])
    assert "finished" in capsys.readouterr().out
    cli.main(["plot", str(run), "--out", str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").stat().st_size > 1000
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--resume", str(tmp_path / "missing"), "--quiet"])
    assert e.value.code == 2


def test_render_refuses_a_vector_environment(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["render", "--env", "tmaze_5", "--out", "unused.png"])
    assert e.value.code == 2 and "no image observation" in capsys.readouterr().err


@pytest.mark.slow
def test_tensorboard_logging_one_run_per_set_and_seed(tmp_path):
    pytest.importorskip("tensorboardX")
    from pobax.eval import train

    cfg = TrainConfig(env="tmaze_5", memory="memoryless", hidden_size=8, num_envs=4, num_steps=16,
                      num_minibatches=2, total_steps=4 * 16 * 2, num_seeds=2, lr=(2.5e-3, 2.5e-4), num_chunks=2)
    train(cfg, tmp_path / "run", progress=False, loggers=("tensorboard",))
    dirs = sorted(p.name for p in (tmp_path / "run" / "tensorboard").iterdir())
    assert dirs == ["set0-seed0", "set0-seed1", "set1-seed0", "set1-seed1"]
    assert all(any((tmp_path / "run" / "tensorboard" / d).glob("events.*")) for d in dirs)
    with pytest.raises(ValueError, match="Unknown logger"):
        train(cfg, tmp_path / "other", progress=False, loggers=("mlflow",))
    assert not (tmp_path / "other").exists()  # refused before anything was written


def test_memory_estimate_and_program_split():
    import dataclasses

    from pobax.eval._sweep import _parts, estimate_run_bytes

    cfg = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2)
    small, big = estimate_run_bytes(cfg), estimate_run_bytes(dataclasses.replace(cfg, num_envs=16))
    assert 0 < small < big <= 4 * small + 4096  # the state and trajectory grow with the environments
    grid = dataclasses.replace(cfg, lr=(1e-3, 1e-4, 1e-5), lambda0=(0.5, 0.9), num_seeds=2)  # 12 runs
    parts = _parts(grid, max_runs=4)
    assert [p.lr for p in parts] == [(1e-3,), (1e-4,), (1e-5,)]  # split along the longest axis, 4 runs each
    assert _parts(grid, max_runs=None) == [grid] and _parts(grid, max_runs=12) == [grid]
