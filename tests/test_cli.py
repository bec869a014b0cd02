import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import cli
from _hostile import refused
from pobax._cli.args import _train_config
from pobax._cli.training import gap_steps_note

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--env", "tmaze_3", "--hidden-size", "8", "--num-envs", "2", "--num-minibatches", "2",
         "--num-steps", "16", "--total-steps", "128", "--num-seeds", "2", "--num-chunks", "2", "--quiet"]


def test_train_round_trip(tmp_path, capsys):
    out = tmp_path / "run"
    cli.main(["train", *SMALL, "--memory", "gru", "--action-concat", "--lr", "1e-3", "1e-4", "--out", str(out)])
    printed = capsys.readouterr().out
    assert "set 0" in printed and "set 1" in printed and "discounted" in printed
    config = json.loads((out / "config.json").read_text())
    assert config["config"]["env"] == "tmaze_3" and config["config"]["lr"] == [1e-3, 1e-4]
    assert [s["lr"] for s in config["hyperparameter_sets"]] == [1e-3, 1e-4]
    metrics = pd.read_csv(out / "metrics.csv")
    assert {"hp_index", "seed", "env_step", "return", "disc_return", "pg_loss", "entropy", "approx_kl",
            "clip_frac", "lr_now", "ep_length", "nonfinite"} <= set(metrics.columns)
    assert "steps_per_s" not in metrics.columns  # timing is not a metric: timing.csv
    assert len(metrics) == 2 * 2 * 4  # sets × seeds × updates
    assert len(list((out / "metrics").glob("*.csv"))) == 2  # one file per chunk
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["sets"]) == 2 and len(summary["sets"][0]["disc_return"]["per_seed"]) == 2
    assert (out / "model.eqx").stat().st_size > 0
    # never overwrite results: the same --out again is an error, and the files are untouched
    before = (out / "metrics.csv").read_bytes()
    with pytest.raises(SystemExit) as e:
        cli.main(["train", *SMALL, "--out", str(out)])
    assert e.value.code == 2
    assert "already exists" in capsys.readouterr().err
    assert (out / "metrics.csv").read_bytes() == before
    assert not list(out.glob(".*.tmp"))


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env", "tmaze10"], "Did you mean 'tmaze_10'"),
        (["--observability", "perfect_memory"], "it has: partial, full"),
        (["--num-envs", "6"], "--num-envs (6) must be divisible by --num-minibatches (4)"),
        (["--total-steps", "100"], "--total-steps (100) is smaller than one update"),
        (["--num-steps", "0"], "--num-steps must be a positive integer"),
        (["--rollout-unroll", "0"], "--rollout-unroll must be a positive integer"),
        (["--lambda0", "1.5"], "--lambda0 values must be in [0.0, 1.0]"),
        (["--lr", "0"], "--lr values must be in (0.0, 1.0] and finite, got 0.0"),
        (["--lr", "inf"], "--lr values must be in (0.0, 1.0] and finite, got inf"),
        (["--lr", "2.5e-4", "1e30"], "--lr values must be in (0.0, 1.0] and finite, got 1e+30"),
        (["--vf-coeff", "nan"], "--vf-coeff values must be >= 0.0 and finite, got nan"),
        (["--clip-eps", "-0.1"], "--clip-eps values must be > 0.0"),
        (["--entropy-coeff", "-1"], "--entropy-coeff values must be >= 0.0"),
        (["--memory", "trxl", "--num-steps", "100"], "--num-steps (100) must be a multiple of --window-grad (64)"),
        (["--encoder", "egocentric"], "encoder 'egocentric' needs a map observation (H, W, C), got shape (4,)"),
        (["--env", "Navix-DMLab-Maze-02-v0", "--observability", "full", "--encoder", "small_cnn"],
         "encoder 'small_cnn' is for images of at most 20 px a side (stride 1 keeps every pixel), got 37x61"),
    ],
)
def test_validation_errors_are_one_line_exit_2(tmp_path, capsys, args, message):
    refused(capsys, ["train", *args, "--out", tmp_path / "r"], message)
    assert not (tmp_path / "r").exists()  # nothing was created before validation


def test_a_validation_error_is_one_line_from_a_fresh_process(tmp_path):
    """As above through the interpreter's own entry (imports' warnings, the exit status), in an empty environment."""
    proc = subprocess.run([sys.executable, str(ROOT / "cli.py"), "train", "--env", "tmaze10", "--out",
                           str(tmp_path / "r")], capture_output=True, text=True, cwd=tmp_path,
                          env={"JAX_PLATFORMS": "cpu", "PATH": ""})
    assert proc.returncode == 2, proc.stderr
    assert "Did you mean 'tmaze_10'" in proc.stderr and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and proc.stdout == ""
    assert not (tmp_path / "r").exists()


def test_envs_lists_tmaze(capsys):
    cli.main(["envs"])
    assert "tmaze_{n}" in capsys.readouterr().out


@pytest.mark.slow
def test_gap_at_its_default_steps_names_the_benchmark_budget(tmp_path, capsys):
    """`pobax gap` trains 150,000 steps per run unless told otherwise; where the environment's benchmark budget is
    longer it says so after the report (once, on stderr; a refused command stays one line), and says nothing once
    --total-steps is given. T-Maze 10's floor alone, on one seed: its 150,000 steps take seconds."""
    from pobax.eval import format_gap

    tiny = ["--env", "tmaze_10", "--agents", "floor", "--num-seeds", "1", "--hidden-size", "8", "--num-envs", "256",
            "--num-steps", "64", "--num-minibatches", "1", "--update-epochs", "1", "--fast-compile", "--quiet"]
    cli.main(["gap", *tiny, "--out", str(tmp_path / "default")])
    captured = capsys.readouterr()
    assert captured.out == format_gap(json.loads((tmp_path / "default" / "gap.json").read_text())) + "\n"
    assert "150,000 steps per run" in captured.err and "1,000,000 steps × 30 seeds" in captured.err
    assert captured.err.count("note") == 1
    cli.main(["gap", *tiny, "--total-steps", "150000", "--out", str(tmp_path / "default")])  # reuses the run
    captured = capsys.readouterr()
    assert "note" not in captured.err and "floor" in captured.out  # the same steps, but given
    config = json.loads((tmp_path / "default" / "floor" / "config.json").read_text())["config"]
    assert config["total_steps"] == 150_000 and config["num_envs"] == 256  # the default, and the flags given
    assert gap_steps_note("battleship_10", 10_000_000) is None


@pytest.mark.parametrize("argv, given", [
    (["--lr", "2.5e-4", "--no-anneal-lr"], {"lr", "anneal_lr"}),  # a default value given explicitly counts
    (["--hidden-size=8", "--unroll", "2", "--quiet"], {"hidden_size", "unroll"}),  # --quiet is not TrainConfig's
    (["--encoder", "flatten", "--env", "tmaze_5"], {"encoder", "env"}),
    ([], set()),
])
def test_the_fields_given_are_those_tyro_read(argv, given):
    """Which training flags were given comes from tyro's own parse (parsed again over shifted defaults), never from
    reading argv by hand."""
    import tyro

    cmd = tyro.cli(cli.Train, args=argv)
    assert cli._given_fields(cmd, argv) == given


def test_flags_given_with_their_default_value_override_a_preset(tmp_path):
    import tyro

    (tmp_path / "p.json").write_text(json.dumps({"preset": {"lr": 1e-3, "hidden_size": 32, "anneal_lr": False}}))
    argv = ["--preset", str(tmp_path / "p.json"), "--lr", "2.5e-4", "--anneal-lr"]
    cmd = tyro.cli(cli.Train, args=argv)
    cfg = _train_config(cmd, cli._given_fields(cmd, argv))
    assert cfg.lr == (2.5e-4,) and cfg.anneal_lr is True and cfg.hidden_size == 32


@pytest.mark.slow  # 19 s on 2 cores: trains through every command
def test_env_options_reach_the_environment_everywhere_and_bad_ones_exit_2(tmp_path, capsys):
    """--env-options KEY=VALUE are the environment's constructor arguments: the run trains in that environment,
    records them, and reading the run back (evaluation, load_run) builds the same one; a malformed item or an
    argument the environment does not take is one line and exit 2, before a run directory is written."""
    from pobax.env import make
    from pobax.eval import load_run

    tiny = ["--hidden-size", "8", "--num-envs", "2", "--num-minibatches", "2", "--num-steps", "16",
            "--total-steps", "64", "--num-seeds", "1", "--num-chunks", "1", "--quiet"]
    out = tmp_path / "run"
    cli.main(["train", "--env", "rocksample_5_5", "--env-options", "map_seed=3", *tiny, "--out", str(out)])
    assert json.loads((out / "config.json").read_text())["config"]["env_options"] == ["map_seed=3"]
    run = load_run(out)
    seeded, default = (make("rocksample_5_5", map_seed=s, wrappers=False) for s in (3, 0))
    rocks = lambda env: np.asarray(env.rock_positions).tolist()  # noqa: E731
    assert rocks(seeded) != rocks(default)  # the option changes the environment...
    assert rocks(run.env.unwrapped) == rocks(seeded)  # ...and the run read back has it
    for bad, says in ((["map_seed"], "KEY=VALUE"), (["no_such_arg=1"], "no_such_arg")):
        with pytest.raises(SystemExit) as e:
            cli.main(["train", "--env", "rocksample_5_5", "--env-options", *bad, *tiny, "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and says in err and "--env-options" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "x").exists()
    # a benchmark with the option says so in its table
    cli.main(["benchmark", "--envs", "rocksample_5_5", "--agents", "floor", "--budget", "smoke", "--env-options",
              "map_seed=3", "--out", str(tmp_path / "bench")])
    assert "| floor (memoryless, partial) [map_seed=3] |" in (tmp_path / "bench" / "benchmark.md").read_text()
