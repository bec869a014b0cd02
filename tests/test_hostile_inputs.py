"""Bad input, tried as a hostile but fair user would: numbers too large to represent or to fit, malformed options,
user cells that misbehave, and the smaller promises (one line, exit 2, nothing left behind). Tiny T-Maze 5 runs on
the CPU (`_hostile.py`)."""


import dataclasses
import io
import json
import math
import os
import re
import subprocess
import sys
import textwrap
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import cli
from pobax.agent import validate
from pobax.env import AbstractWrapper, make
from pobax.eval import RunDir, load_run, train
from pobax.eval._files import CheckpointError
from pobax.eval._listing import list_runs

from _hostile import CFG, ROOT, TINY, copy, digest, refused, unseal, write_summary


# --- 1. numbers the program cannot represent, or memory it cannot have -----------------------------------------

@pytest.mark.parametrize("args, message", [
    (["--hidden-size", "1000000000"], "--hidden-size 1000000000: the runs need at least"),
    (["--num-seeds", "1000000000"], "--num-seeds 1,000,000,000"),
    (["--num-seeds", "100000000"], "--num-seeds 100000000: the runs need at least"),
    (["--total-steps", "1099511627776"], "--total-steps 1,099,511,627,776 is 2,147,483,648 updates"),
    (["--vf-coeff", "1e39"], "--vf-coeff values must be >= 0.0 and finite, got 1e+39 (inf in float32"),
    (["--lr", "1e-50"], "--lr values must be in (0.0, 1.0] and finite, got 1e-50 (0 in float32"),
    # subnormal in float32: XLA flushed them to 0, so the run trained with a step size (or reward scale) of 0
    (["--lr", "1e-40"], "--lr 1e-40 is below float32's smallest normal number"),
    (["--reward-scale", "1e-40"], "--reward-scale 1e-40 is below float32's smallest normal number"),
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
    ("rocksample_46340_2000000000", "and 1 to 65,536 rocks"),  # a dict of 2e9 cells grew until the OOM killer
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


@pytest.mark.parametrize("env, options, message", [
    ("rocksample_5_3", dict(half_efficiency_distance=1e-40), "half_efficiency_distance must be a positive float32"),
    ("battleship_10", dict(proposals=0), "proposals (placements drawn at once"),  # argmax of an empty sequence
    ("battleship_10", dict(proposals=10**10), "integer in [1, 4096]"),  # out of device memory (16 TB)
    ("ant_pixels", dict(image_size=0), "image_size must be an integer in [1, 512]"),  # an IndexError traceback
    ("ant_pixels", dict(supersample=0), "supersample must be an integer in [1, 16]"),  # black frames, trained on
    ("ant_pixels", dict(image_size=3 * 10**9), "image_size must be"),  # the OOM killer, a run directory left
    ("ant_pixels", dict(image_size=256, supersample=4), "image_size × supersample = 1024 pixels a side"),
])
def test_environment_options_beyond_what_the_environment_computes_are_refused(env, options, message):
    """Options an environment took and computed wrongly with (a sensor dividing by a float32 zero: never right at
    distance 0), failed on deep inside (a traceback), or ran out of memory on."""
    if env == "ant_pixels":
        pytest.importorskip("brax")
    with pytest.raises(ValueError) as e:
        make(env, **options)
    assert message in str(e.value) and "\n" not in str(e.value), e.value


def test_a_seed_at_the_top_of_its_range_reruns_on_fresh_seeds_of_its_range():
    """`--seed 4294967295` under the paper's protocol or `gap --sweep`: the whole sweep trained, then the rerun's base
    seed (10,000 on) was refused as out of range, a seed the user never gave. It wraps, and stays disjoint."""
    from pobax.eval._protocol import evaluation_config, evaluation_keys, selection_keys

    sweep = dataclasses.replace(CFG, seed=2**32 - 1, num_seeds=5)
    rerun = evaluation_config(sweep, {"lr": 2.5e-4, "lambda0": 0.95}, 30)
    validate(rerun)
    assert rerun.seed == 9_999 and not selection_keys(sweep) & evaluation_keys(rerun)


def test_the_memory_bound_counts_every_square_layer_of_the_network():
    """The bound (a lower one) counted one hidden × hidden layer where the GRU agent has eight (its heads' two, its
    six gate blocks): at hidden 20,000 it asked 6 GiB of a machine where the parameters alone take 48 GiB, which the
    process then tried to allocate."""
    from pobax.agent import make_model
    from pobax.eval._bounds import train_bytes

    for memory, double in (("gru", False), ("gru", True), ("memoryless", False), ("lstm", False)):
        cfg = dataclasses.replace(CFG, memory=memory, double_critic=double, num_seeds=1, hidden_size=2048,
                                  num_envs=1, num_steps=1)  # (the rollout's share of the bound: a few numbers)
        model = eqx.filter_eval_shape(make_model, cfg, make("tmaze_5"), jax.random.key(0))  # shapes only
        params = sum(x.size for x in jax.tree.leaves(model) if isinstance(x, jax.ShapeDtypeStruct))
        bound = train_bytes(cfg) / 16  # parameters, gradient and two moments, float32
        assert 0.97 * params <= bound <= params, (memory, double, params, bound)


@pytest.mark.slow
def test_returns_no_episode_gave_are_null_in_strict_json_and_nan_when_read(tmp_path, capsys):
    """A run in which no episode ended wrote NaN into summary.json (and gap.json, sweep.json): not JSON, which other
    tools (jq, JavaScript) refuse. Written as null; pobax reads a summary's back as NaN, as training returned it."""
    run = tmp_path / "r"
    cfg = dataclasses.replace(CFG, env="tmaze_300", total_steps=1024, num_envs=4, num_steps=16, num_seeds=2)
    assert math.isnan(train(cfg, run, progress=False).summary["sets"][0]["disc_return"]["mean"])

    def no_constants(name):
        raise ValueError(f"{name} in summary.json")

    text = (run / "summary.json").read_text()
    assert json.loads(text, parse_constant=no_constants)["sets"][0]["disc_return"]["mean"] is None
    summary = RunDir(run).read_summary()  # its seal checked as written
    assert math.isnan(summary["sets"][0]["disc_return"]["mean"]) and math.isnan(summary["sets"][0]["return"]["ci_low"])
    cli.main(["results", "--root", str(tmp_path)])
    assert capsys.readouterr().out.splitlines()[1].endswith(" finished       no episode ended")


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


# --- 2. the smaller promises ------------------------------------------------------------------------------------

def test_user_cells_that_misbehave(user_cells, capsys):
    out = user_cells / "r"
    refused(capsys, ["train", *TINY, "--memory", "cells:Wide", "--out", out],
            "Wide(in_size=4, hidden_size=8) returns outputs of shape (4, 11)", "(time, out_size) = (4, 8)",
            "check_memory")
    refused(capsys, ["train", *TINY, "--memory", "cells:IntOut", "--out", out], "returns int32 outputs",
            "real floats")
    refused(capsys, ["train", *TINY, "--memory", "cells:CarryGrows", "--out", out],
            "returns a carry not laid out like its init_carry()")
    refused(capsys, ["train", *TINY, "--memory", "cells:NonStatic", "--out", out],
            "field .in_size is a int, not an array", "eqx.field(static=True)")
    refused(capsys, ["train", *TINY, "--memory", "quitter:Cell", "--out", out], "called sys.exit(0)")
    refused(capsys, ["train", *TINY, "--memory", "cells:Triple", "--out", out],  # was "too many values to unpack"
            "Memory 'cells:Triple'", "returns a tuple of 3 from __call__(carry, xs, starts)")
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


def test_a_full_disk_says_how_to_resume_once(tmp_path, stopped, capsys, monkeypatch):
    """A full disk while training said how to continue, then the command line's own advice for a full disk after it
    ("make room, then continue with ...; free disk space and run the command again")."""
    import errno

    from pobax.eval._results import RunDir

    def full(self, index, df):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path / "metrics" / f"{index:05d}.csv"))

    run = copy(stopped, tmp_path / "r")
    monkeypatch.setattr(RunDir, "write_chunk", full)
    err = refused(capsys, ["train", "--resume", run], "No space left on device",
                  f"the last checkpoint is in {run}: make room, then continue with pobax train --resume {run}",
                  started=True)
    assert err.strip().endswith(f"pobax train --resume {run}") and "free disk space" not in err, err


@pytest.mark.slow
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
    assert err.strip().endswith(f"checkpoint): pobax {' '.join(nan)} --out {tmp_path / 's2'}"), err


def test_plot_and_load_run_refuse_damaged_metrics(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "metrics.csv").write_text("garbage\n1\n")
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], "metrics.csv' differs from the file its run finished")
    with pytest.raises(ValueError, match="metrics.csv' differs from the file its run finished"):
        load_run(run)
    unseal(run)
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


@pytest.mark.slow
def test_a_truncated_model_or_normaliser_is_refused_by_eval_and_render(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "model.eqx").write_bytes((run / "model.eqx").read_bytes()[:1000])
    refused(capsys, ["eval", run], "model.eqx' differs from the file its run finished with")  # (its seal)
    unseal(run)
    refused(capsys, ["eval", run], "model.eqx' is damaged or does not match the run's configuration")
    refused(capsys, ["render", run, "--out", tmp_path / "e.gif"], "model.eqx' is damaged")
    normed = tmp_path / "n"
    train(dataclasses.replace(CFG, normalize_obs=True, num_seeds=1), normed, progress=False)
    (normed / "obs_norm.eqx").write_bytes((normed / "obs_norm.eqx").read_bytes()[:10])  # was a traceback
    refused(capsys, ["eval", normed], "obs_norm.eqx' differs from the file its run finished with")
    unseal(normed)
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


@pytest.mark.slow
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
    unseal(run)  # from before the seal (a sealing run's summary without one is refused: its seal removed)
    (run / "summary.json").write_text('{"x": 1}')  # valid JSON of another shape: was a KeyError traceback
    cli.main(["plot", str(run), "--best", "--out", str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").stat().st_size > 0


@pytest.mark.parametrize("text", ["[1]", '{"best_by_auc": null}', '{"best_by_auc": 99}'])
def test_eval_and_render_refuse_a_summary_json_of_another_shape(tmp_path, finished, capsys, text):
    """A finished run's summary.json edited into valid JSON of another shape: eval and render ended in an
    AttributeError or TypeError traceback, or eval wrote "best_by_auc": 99 (a set the run does not have) into its
    results; load_run, which both read it through, refuses it naming the file."""
    run = copy(finished, tmp_path / "r")
    unseal(run)  # from before the seal (a sealing run's summary without one is refused: its seal removed)
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
    with pytest.raises(ValueError, match="model.eqx' differs from the file its run finished with"):
        load_run(run)  # the summary's seal sees it first; sealed with it, as a run could have saved it:
    write_summary(run, json.loads((run / "summary.json").read_text()))
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
        write_summary(run, summary)
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


# --- 3. options that changed behaviour silently, or left something behind ---------------------------------------

@pytest.mark.parametrize("name", ["rocksample_015_15", "tmaze_05", "battleship_010", "tmaze_\u0663"])
def test_an_environment_id_has_one_spelling(name):
    """rocksample_015_15 built rocksample_15_15's environment with the generic family's settings (hidden 256, the GRU
    at lr 2.5e-4 instead of 512 and 2.5e-3): an ID never changes behaviour silently, so another spelling is unknown."""
    with pytest.raises(ValueError, match="Unknown environment"):
        make(name)


@pytest.mark.parametrize("args, message", [
    (["--env-options", "wrappers=false"], "wrappers is not an environment option"),  # trained without a time limit
    (["--env-options", "observability=full"], "observability is not an environment option"),  # was a TypeError
    (["--env-options", "time_limit=5", "time_limit=null"], "gives time_limit twice"),  # the last one won
    (["--env", "battleship_10", "--env-options", "time_limit=1000"], "ends every episode within 100 steps itself"),
    (["--reward-scale", "1e-50"], "--reward-scale must be > 0 in float32"),  # trained on rewards of 0
    (["--total-steps", "0"], "--total-steps must be a positive integer, got 0"),  # (no int32 bound: updates count)
    (["--axis", "gating=maybe"], "'maybe' is not a boolean"),  # was gating=False
    (["--axis", "hidden_size=8", "hidden_size=16"], "gives hidden_size twice"),  # 8 was dropped
    (["--axis", "unroll=1,x"], "cannot read 'x' as int"),  # was a TypeError traceback
    (["--axis", "env_options=time_limit=5"], "which --axis cannot list"),  # was split into characters
    (["--axis", "encoder=cnn"], "'cnn' is not one of auto, flatten"),
    (["--env-options", "length=3"], "length is set by the ID itself"),  # "got multiple values for keyword"
    # a value given twice trained its sets or program twice; selection across these axes selected nothing of the agent
    (["--lr", "2.5e-4", "0.00025000001"], "--lr gives 0.00025 more than once (in float32"),
    (["--axis", "hidden_size=8,16,8"], "--axis hidden_size gives 8 more than once"),
    (["--axis", "env=tmaze_5,tmaze_6"], "returns of different environments are not comparable"),
    (["--axis", "observability=partial,full"], "another observability is another problem"),
    (["--axis", "seed=1,2"], "selecting among seeds selects luck"),
    # a flag no agent of the command reads: a GRU trained as if it were the λ-discrepancy agent or a Transformer-XL
    (["--ld-weight", "0.25"], "--ld-weight is read only by the λ-discrepancy agent (--double-critic)"),
    (["--lambda1", "0.5", "0.95"], "--lambda1 is read only by the λ-discrepancy agent"),  # two identical sets
    (["--num-heads", "2"], "--num-heads is read only by the Transformer-XL memory (--memory trxl) and this "
                           "command trains gru with one critic"),
    (["--memory", "trxl", "--window-grad", "16", "--no-gating", "--gating-bias", "3"],
     "--gating-bias is read only by the Transformer-XL memory's gates (--memory trxl --gating)"),
    (["--memory", "lstm", "--no-gating"], "--gating/--no-gating is read only by the Transformer-XL memory"),
    (["--memory", "trxl", "--extra-dense"], "--extra-dense/--no-extra-dense is read only by the GRU memory"),
    (["--axis", "window_mem=4,8"], "--axis window_mem is read only by the Transformer-XL memory"),
    (["--previous-action", "applied"], "--previous-action is read only by an agent given the previous action "
                                        "(--action-concat) and this command trains gru with one critic without the "
                                        "previous action"),
    (["--axis", "memory=gru,lstm", "--embed-size", "16"], "this command trains gru with one critic, lstm with one"),
])
def test_options_that_changed_behaviour_silently_are_refused(tmp_path, capsys, args, message):
    command = "sweep" if args[0] == "--axis" else "train"
    refused(capsys, [command, *TINY, *args, "--out", tmp_path / "o"], message)
    assert not (tmp_path / "o").exists()


def test_a_float_field_given_an_integer_too_large_for_a_float_is_refused(tmp_path, capsys):
    """A preset's {"lr": 10**400} was a TypeError traceback (np.isfinite on a Python int)."""
    for field, message in (("gating_bias", "gating_bias is an integer of about 401 digits, too large for a float"),
                           ("lr", "lr is an integer of about 401 digits, too large for a float")):
        (tmp_path / "p.json").write_text(f'{{"{field}": 1' + "0" * 400 + "}")
        refused(capsys, ["train", *TINY, "--preset", tmp_path / "p.json", "--out", tmp_path / "o"], message)
    for text, message in ((b"\xff\xfe", "is not UTF-8 text"), (b"[" * 100_000, "nests too deeply"),
                          (b'{"hidden_size": 1' + b"0" * 5000 + b"}", "is not valid JSON (Exceeds the limit")):
        (tmp_path / "p.json").write_bytes(text)  # were UnicodeDecodeError, RecursionError, ValueError tracebacks
        refused(capsys, ["train", *TINY, "--preset", tmp_path / "p.json", "--out", tmp_path / "o"], message)
    assert not (tmp_path / "o").exists()


def test_sweep_and_gap_refuse_an_environment_that_does_not_build_before_claiming_out(tmp_path, capsys):
    """`sweep --env nosuch` left pobax-sweep.json in --out, which then refused the corrected command as another
    call's; a later program's value that cannot train (`--axis memory=gru,nosuch`) is refused before the first
    program trains."""
    for command, args, message in (
            ("sweep", ["--env", "nosuch"], "Unknown environment 'nosuch'"),
            ("sweep", ["--observability", "perfect_memory"], "has no observability 'perfect_memory'"),
            ("sweep", ["--axis", "memory=gru,nosuch"], "Unknown memory 'nosuch'"),
            ("gap", ["--env-options", "foo=1"], "unexpected keyword argument 'foo'"),
            ("gap", ["--agents"], "--agents needs at least one agent"),  # wrote an empty report over the last
            ("benchmark", ["--agents"], "--agents needs at least one agent")):
        argv = [command, *(TINY if command != "benchmark" else ["--envs", "tmaze_5", "--budget", "smoke"]), *args]
        refused(capsys, [*argv, "--out", tmp_path / "o"], message)
        assert not (tmp_path / "o").exists(), argv


def test_tyros_errors_are_one_line(tmp_path, capsys):
    """tyro's parse errors were boxes of 5-20 lines."""
    refused(capsys, ["train", "--total-steps", "1e6"], "Error parsing --total-steps", "(see pobax train --help)")
    refused(capsys, ["benchmark", "--budget", "bogus"], "invalid choice 'bogus' for argument '--budget'")
    refused(capsys, ["train", "--num-processes", "0", "--process-id", "0"], "--num-processes must be a positive")
    refused(capsys, ["train", "--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"],
            "--coordinator takes process 0's HOST:PORT")  # was an IndexError inside jax.distributed


def test_plot_refused_after_it_made_folders_leaves_none(tmp_path, finished, capsys):
    refused(capsys, ["plot", finished, "--metric", "nosuch", "--out", tmp_path / "a" / "b" / "c.png"], "nosuch")
    assert not (tmp_path / "a").exists()


def test_evaluate_and_pick_refuse_counts_that_are_not_integers(finished):
    from pobax.eval import EvalError, evaluate, load_run as load
    from pobax.eval._load import RunLoadError

    from pobax.eval._episodes import check_count

    for kw in (dict(episodes=True), dict(max_steps=True), dict(max_steps=0)):  # True was 1 episode, an iota error
        with pytest.raises(EvalError, match="must be a positive integer"):
            evaluate(finished, save=False, **kw)
    with pytest.raises(EvalError, match="--episodes must be a positive integer .* got 2.5"):
        check_count("--episodes", 2.5)  # (beartype refuses a float where the tests run; without it, this does)
    with pytest.raises(RunLoadError, match="seed must be an integer index, got True"):
        load(finished).pick(seed=True)


def test_a_user_cell_declaring_impossible_sizes_is_refused(tmp_path, capsys, user_cells):
    """A declared out_size the network cannot be built with was an OverflowError, IndexError or TypeError inside
    pobax; a cell without in_size/out_size the abstract-class TypeError."""
    (user_cells / "sizes.py").write_text(textwrap.dedent("""
        from cells import Wide
        from pobax.memory import AbstractMemory

        class Sized(Wide):
            def __init__(self, in_size, hidden_size, *, key):
                super().__init__(in_size, hidden_size, key=key)
                self.out_size = self.OUT

        class Huge(Sized):
            OUT = 10**12

        class Zero(Sized):
            OUT = 0

        class Text(Sized):
            OUT = "8"

        class NoSizes(AbstractMemory):
            def __init__(self, in_size, hidden_size, *, key):
                pass
    """))
    for name, message in (("Huge", "Huge.out_size is 1000000000000"), ("Zero", "Zero.out_size is 0"),
                          ("Text", "Text.out_size is '8'"), ("NoSizes", "abstract class")):
        refused(capsys, ["train", *TINY, "--memory", f"sizes:{name}", "--out", tmp_path / "o"], message)
    assert not (tmp_path / "o").exists()


def test_a_flag_is_read_where_one_agent_of_the_command_reads_it():
    """The refusal above counts every agent a sweep's axes train, and names what each field's agent is."""
    from pobax._cli.args import _check_read
    from pobax.agent import unread_fields

    _check_read(CFG, frozenset({"num_heads"}), {"memory": ["gru", "trxl"]})
    _check_read(CFG, frozenset({"ld_weight", "alpha"}), {"double_critic": [False, True]})
    _check_read(dataclasses.replace(CFG, memory="trxl", gating=False), frozenset({"gating_bias"}), {"gating": [True]})
    _check_read(CFG, frozenset({"previous_action"}), {"action_concat": [False, True]})
    _check_read(dataclasses.replace(CFG, memory="trxl", double_critic=True), frozenset({"window_mem", "lambda1"}))
    assert unread_fields(CFG, ["ld_weight", "lr", "embed_size", "extra_dense"]) == {
        "ld_weight": ("the λ-discrepancy agent", "--double-critic"),
        "embed_size": ("the Transformer-XL memory", "--memory trxl")}
    assert unread_fields(dataclasses.replace(CFG, memory="memax_or_mine:Cell"), ["extra_dense"]) == {
        "extra_dense": ("the GRU memory", "--memory gru")}


@pytest.mark.parametrize("args, message", [
    (["gap", "--env", "tmaze_5", "--agents", "floor", "gru", "--num-heads", "2"],
     "--num-heads is read only by the Transformer-XL memory, and no agent trained here has it (floor, gru): add trxl"),
    (["benchmark", "--envs", "tmaze_5", "rocksample_11_11", "--agents", "floor", "gru", "--budget", "smoke", "--alpha",
      "0.5"], "no agent trained here has it (floor, gru): add ld to --agents"),
    (["benchmark", "--envs", "tmaze_5", "--agents", "trxl", "--budget", "smoke", "--protocol", "paper",
      "--extra-dense"], "--extra-dense is read only by the GRU memory"),
])
def test_gap_and_benchmark_refuse_a_flag_none_of_their_agents_reads(tmp_path, capsys, args, message):
    refused(capsys, [*args, "--out", tmp_path / "o"], message)
    assert not (tmp_path / "o").exists()


def test_gap_from_python_refuses_an_override_none_of_its_agents_reads(tmp_path):
    from pobax.agent import ConfigError, TrainConfig
    from pobax.agent._network import check_overrides_read
    from pobax.eval import gap_report

    with pytest.raises(ConfigError, match="--ld-weight is read only by the λ-discrepancy agent.*add ld to --agents"):
        gap_report("tmaze_5", agents=("floor", "gru"), overrides={"ld_weight": 0.5}, out=tmp_path / "g")
    with pytest.raises(ConfigError, match="--window-mem is read only by the Transformer-XL memory"):
        gap_report("tmaze_5", agents=("floor",), base=TrainConfig(window_mem=8), out=tmp_path / "g")
    assert not (tmp_path / "g").exists()
    check_overrides_read([("floor", CFG), ("ld", dataclasses.replace(CFG, double_critic=True))], {"ld_weight": 0.5})


# --- 4. from Python -----------------------------------------------------------------------------------------------

def test_a_discrete_action_outside_the_action_space_changes_nothing():
    """Battleship read cell 100 as cell 99's ship without marking it fired: shot forever, it won the game; RockSample
    read -5 as a move north and 16+ as checking its last rock."""
    bs = make("battleship_10", wrappers=False)
    state, _ = bs.reset(key=jax.random.key(4))
    for action in (100, -1, 1000):
        after, ts = bs.step(state, jnp.asarray(action, jnp.int32), key=jax.random.key(1))
        assert float(ts.reward) == -1.0 and not bool(ts.terminated)  # a wasted shot
        assert int(after.fired.sum()) == 0 and after.cells_left.tolist() == state.cells_left.tolist()
    rs = make("rocksample_11_11", wrappers=False)
    state, _ = rs.reset(key=jax.random.key(0))
    for action in (-5, 16, 1000):
        after, ts = rs.step(state, jnp.asarray(action, jnp.int32), key=jax.random.key(1))
        assert after.pos.tolist() == state.pos.tolist() and float(ts.reward) == 0.0 and int(after.observed) == -1


def test_numpy_numbers_are_written_and_configured_as_numbers(tmp_path):
    """NumPy scalars in a TrainConfig were written to config.json as strings ("0.0025"): the run trained, then never
    loaded. (The tests' beartype refuses NumPy scalars in TrainConfig itself; without it they become Python's.)"""
    from pobax.agent._config import _plain
    from pobax.eval._files import write_json

    assert [_plain(v) for v in (np.int64(8), np.float64(2.5e-3), np.array(0.9), np.bool_(True), np.arange(2))] == \
        [8, 2.5e-3, 0.9, True, (0, 1)]
    assert type(_plain(np.int64(8))) is int and type(_plain(np.bool_(True))) is bool
    write_json(tmp_path / "c.json", {"lr": [np.float32(0.5)], "num_seeds": np.int64(2), "shape": np.zeros(2)})
    assert json.loads((tmp_path / "c.json").read_text()) == {"lr": [0.5], "num_seeds": 2, "shape": [0.0, 0.0]}


def test_registry_and_gap_refuse_what_they_would_silently_ignore():
    from pobax.env import EnvFamily, register
    from pobax.env._tmaze import TMaze
    from pobax.eval import gap_report

    with pytest.raises(ValueError, match="'tmaze_{n}': that template is already registered"):
        register(EnvFamily(template="tmaze_{n}", pattern=r"tmaze_(?P<length>\d+)", observabilities=("partial",),
                           build=lambda observability, length: TMaze(length + 3, observability), categories=(),
                           max_steps=1000, registered=()))
    with pytest.raises(ValueError, match="'tmaze_10' is already an ID of 'tmaze_{n}'"):
        register(EnvFamily(template="my_maze", pattern=r"my_maze|tmaze_10", observabilities=("partial",),
                           build=lambda observability: TMaze(3, observability), categories=(), max_steps=10,
                           registered=("tmaze_10",)))
    with pytest.raises(ValueError, match="ends every episode within 100 steps itself"):
        make("battleship_10", time_limit=np.int64(10**6))  # a NumPy count was not compared
    with pytest.raises(ValueError, match="memory, observability is set per agent by the gap report"):
        gap_report("tmaze_5", agents=("floor",), overrides=dict(memory="lstm", observability="full"))  # trained
        # lstm on full, reported as the floor


def test_the_registry_time_limit_follows_an_environment_built_shorter():
    """Only a time_limit given explicitly beyond the environment's own bound is refused: the registry's own (Craftax's
    100,000) follows an environment built with a shorter bound (its max_timesteps=5 was refused)."""
    pytest.importorskip("craftax")
    assert make("craftax_pixels", max_timesteps=5).max_steps_in_episode == 5


def test_results_lists_a_run_whose_name_holds_a_newline_or_undecodable_bytes_on_one_line(tmp_path, finished, capsys):
    """A run directory named with a newline (`--out "$(printf 'a\\nb')"`) split its row of `results` in two, and one
    whose name is not UTF-8 raised UnicodeEncodeError on printing; each is one row, its name escaped."""
    root = tmp_path / "runs"
    root.mkdir()
    copy(finished, root / "a\nb")
    copy(finished, root / "c\udcff")  # the byte 0xff: not UTF-8
    copy(finished, root / "d-plain")
    cli.main(["results", "--root", str(root)])
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 4, lines  # the header and one row per run
    assert lines[1].startswith(str(root) + "/a\\nb ") and lines[2].startswith(str(root) + "/c\\udcff ")
    assert lines[3].startswith(str(root / "d-plain") + " ") and all(" finished " in line for line in lines[1:])


def test_a_path_that_is_not_utf8_prints_escaped_on_a_strict_utf8_stdout(tmp_path, monkeypatch):
    """On a strict UTF-8 stdout (a UTF-8 locale but C.UTF-8's, PYTHONIOENCODING=utf-8) a name that is not UTF-8
    raised UnicodeEncodeError at the first print (`train --out` stopped before training with that error alone)."""
    root = tmp_path / "e\udcff"  # the byte 0xff: not UTF-8
    root.mkdir()
    out = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict")
    monkeypatch.setattr(sys, "stdout", out)
    cli.main(["results", "--root", str(root)])
    out.flush()
    assert out.buffer.getvalue().decode("utf-8") == f"no runs under {tmp_path}/e\\udcff\n"


def test_sweep_from_python_refuses_axes_it_cannot_select_among_or_train(tmp_path):
    """As the command line: an axis not a list (a bare 8 was a TypeError inside itertools), a value twice, an
    axis across which selection by AUC selects nothing of the agent; and a hyperparameter value twice."""
    from pobax.agent import ConfigError
    from pobax.eval import sweep

    for axes, message in (({"hidden_size": 8}, "needs a list of values"), ({"hidden_size": []}, "needs a list"),
                          ({"memory": ["gru", "gru"]}, "gives 'gru' more than once"),
                          ({"env": ["tmaze_5", "tmaze_6"]}, "not comparable"),
                          ({"hiddensize": [8, 16]}, "--axis hiddensize: not a TrainConfig field")):
        with pytest.raises(ValueError, match=message):
            sweep(CFG, out=tmp_path / "o", axes=axes, progress=False)
    with pytest.raises(ConfigError, match="--lambda0 gives 0.5 more than once"):
        validate(dataclasses.replace(CFG, lambda0=(0.5, 0.9, 0.5)))
    assert not (tmp_path / "o").exists()


def test_a_sweep_continued_with_another_split_or_rerun_is_refused_before_training(tmp_path):
    """Continued with another --max-runs, a sweep moved its finished parts aside as incomplete and trained the
    program again; with another --rerun-seeds it trained and then refused. Both are refused before anything trains,
    naming the value that continues it; that value continues it."""
    from pobax.eval import sweep

    cfg = dataclasses.replace(CFG, memory="memoryless", lr=(1e-3, 1e-2), num_seeds=1, num_chunks=1)
    out = tmp_path / "sweep"
    sweep(cfg, out, max_runs=1, rerun_seeds=1, progress=False)
    before = digest(out)
    for kwargs, message in ((dict(max_runs=2), "trained in 2 parts of up to 1 run; this call splits it in 1: pass "
                             "--max-runs 1"), (dict(max_runs=1, rerun_seeds=2), "holds the selected set's re-run "
                             "with 1 seed: pass --rerun-seeds 1")):
        with pytest.raises(ValueError, match=re.escape(message)):
            sweep(cfg, out, progress=False, **kwargs)
        assert digest(out) == before
    assert sweep(cfg, out, max_runs=1, rerun_seeds=1, progress=False)["rerun"]["run_dir"] == str(out / "rerun")
    whole = tmp_path / "whole"
    sweep(cfg, whole, progress=False)
    with pytest.raises(ValueError, match="trained as one program; this call splits it in 2 parts"):
        sweep(cfg, whole, max_runs=1, progress=False)
    assert [p.name for p in (whole / "base").iterdir() if p.name.startswith("part")] == []


def test_write_preset_writes_over_only_a_preset_and_only_values_load_preset_reads(tmp_path):
    """write_preset wrote over any file (a run's config.json, a user's notes) and wrote values that load_preset then
    refused ("lr": "x"); an unknown hyperparameter was dropped without a word."""
    from pobax.agent import ConfigError, load_preset
    from pobax.eval import write_preset

    notes = tmp_path / "notes.json"
    notes.write_text('{"mine": 1}')
    with pytest.raises(FileExistsError, match="exists and is not a preset file pobax wrote"):
        write_preset(notes, CFG, {"lr": 1e-3})
    assert notes.read_text() == '{"mine": 1}'
    with pytest.raises(ConfigError, match="--lr takes numbers"):
        write_preset(tmp_path / "p.json", CFG, {"lr": "x"})
    with pytest.raises(ConfigError, match="not one: bogus"):
        write_preset(tmp_path / "p.json", CFG, {"bogus": 1})
    assert not (tmp_path / "p.json").exists()
    write_preset(tmp_path / "p.json", CFG, {"lr": 1e-3})
    write_preset(tmp_path / "p.json", CFG, {"lr": 2e-3})  # an earlier preset: written over
    assert load_preset(tmp_path / "p.json")["lr"] == (2e-3,)


def test_a_user_cell_is_checked_before_any_agent_of_a_sweep_gap_or_benchmark_trains(user_cells, capsys):
    """A cell of the wrong output width was refused only when its own agent came to train: the GRU of the sweep, the
    floor of the gap and the benchmark had trained and left their directories."""
    out = user_cells / "o"
    why = "Wide(in_size=4, hidden_size=8) returns outputs of shape (4, 11)"
    refused(capsys, ["sweep", *TINY, "--memory", "gru", "--axis", "memory=gru,cells:Wide", "--out", out], why)
    refused(capsys, ["gap", *TINY, "--agents", "floor", "--memories", "cells:Wide", "--out", out],
            "returns outputs of shape")
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--agents", "floor", "--memories",
                     "cells:Wide", "--out", out], "returns outputs of shape")
    assert not out.exists()


def test_names_with_a_newline_or_a_byte_not_utf8_print_escaped_and_resume_as_printed(tmp_path, capsys):
    """`train --out $'a\\nb'` printed its run directory and its resume command across two lines, and a 0xff byte
    raw; the resume command printed is now one shell word that names the directory."""
    for name in ("a\nb", "x\udcff"):  # (a byte that is not UTF-8 reaches Python as a surrogate)
        run = tmp_path / name
        cli.main(["train", *TINY, "--num-chunks", "4", "--max-chunks", "1", "--out", str(run)])
        out = capsys.readouterr().out
        assert all(line.isprintable() for line in out.splitlines()) and len(out.splitlines()) == 4, out
        assert f"run directory: {tmp_path}/{name.encode('unicode_escape', 'backslashreplace').decode()}" in out
        command = next(line for line in out.splitlines() if "continue with: " in line).split("continue with: ")[1]
        word = command.removeprefix("pobax train --resume ")
        printed = subprocess.run(["bash", "-c", f"printf %s {word}"], capture_output=True).stdout
        assert printed == os.fsencode(run), (word, printed)


@pytest.mark.parametrize("env, options, message", [
    ("battleship_10", {"ship_lengths": [2.5]}, "ship_lengths=[2.5] is not of its type tuple[int, ...]"),  # a trace's
    ("battleship_10", {"ship_lengths": [True]}, "ship_lengths=[True] is not of its type"),  # TypeError; a ship of 1
    ("battleship_10", {"loop_free": "yes"}, "loop_free='yes' is not of its type bool | None"),  # read as True
    ("battleship_10", {"loop_free": 0}, "loop_free=0 is not of its type bool | None"),
    ("rocksample_2_1", {"rock_positions": [[0.7, 1.9]]}, "rock_positions=[[0.7, 1.9]] is not of its type"),  # [[0, 1]]
    ("rocksample_2_1", {"rock_positions": [[[0, 1]]]}, "rock_positions=[[[0, 1]]] is not of its type"),  # reshaped
    ("rocksample_2_1", {"rock_positions": [[2**40, 0]]},  # an OverflowError's traceback, then NumPy's words
     "rock positions inside the grid (rock_positions: integers in [0, 1])"),
])
def test_environment_options_of_another_type_are_refused_not_coerced(env, options, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        make(env, **options)


def test_environment_options_of_their_types_build_from_python_and_the_command_line(tmp_path, capsys):
    env = make("rocksample_2_1", rock_positions=np.array([[0, 1]]), half_efficiency_distance=20, wrappers=False)
    assert env.rock_positions.tolist() == [[0, 1]] and env.half_efficiency_distance == 20
    env = make("battleship_10", ship_lengths=[3, 2], loop_free=True, wrappers=False)
    assert env.ship_lengths == (3, 2) and env.loop_free is True
    refused(capsys, ["train", *TINY[2:], "--env", "battleship_10", "--env-options", "ship_lengths=[2.5]", "--out",
                     tmp_path / "r"], "--env-options ship_lengths=[2.5]", "is not of its type tuple[int, ...]")
    assert not (tmp_path / "r").exists()


def test_a_hyperparameter_array_of_two_dimensions_is_refused_not_flattened():
    """TrainConfig(lr=np.array([[1e-3, 2e-3], [3e-3, 4e-3]])) swept four step sizes, its shape silently lost. (In a
    process of its own: the tests' beartype refuses every array in TrainConfig before it converts them.)"""
    code = ("import numpy as np\n"
            "from pobax.agent import ConfigError, TrainConfig\n"
            "print(TrainConfig(env='tmaze_5', lr=np.array([1e-3, 2e-3])).lr)\n"
            "try:\n"
            "    TrainConfig(env='tmaze_5', lr=np.array([[1e-3, 2e-3], [3e-3, 4e-3]]))\n"
            "except ConfigError as e:\n"
            "    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"}, check=True).stdout.splitlines()
    assert out == ["(0.001, 0.002)", "lr is an array of shape (2, 2); give a number or a list (or 1-D array) of "
                   "them, one per value swept."]
