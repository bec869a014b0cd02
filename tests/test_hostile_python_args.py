"""The Python API's functions under arguments of the wrong kind, as `train`'s are checked: refused in one line
(the exception and what to pass instead) before anything is trained or written, never read as something else (a
string "no" as True, "wandb" as 'w', 'a', ...), never written over a file they did not write, and `~` expanded as a
shell would. One tiny T-Maze 5 run on the CPU, trained once for the module."""

import dataclasses
import json
import os
import types

import numpy as np
import pytest
from PIL import Image

import pobax.eval._animation as animation
import pobax.eval._gap as gap
import pobax.eval._run as run_module
from _hostile import as_a_notebook, copy, digest, refused  # noqa: F401  (the fixture)
from pobax.agent import ConfigError, TrainConfig
from pobax.eval import (BenchmarkError, EvalError, RenderError, RunLoadError, evaluate, gap_report, load_run,
                        merge_results, plot_runs, render_episode, run_benchmark, train)

CFG = TrainConfig(env="tmaze_5", hidden_size=16, total_steps=2048, num_envs=4, num_steps=128, num_seeds=1,
                  num_chunks=4, fast_compile=True)


pytestmark = pytest.mark.usefixtures("as_a_notebook")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished tiny run (`CFG`)."""
    path = tmp_path_factory.mktemp("python-args") / "run"
    train(CFG, path, progress=False)
    return path


def one_line(e: pytest.ExceptionInfo, *fragments: str) -> None:
    message = str(e.value)
    assert "\n" not in message and all(f in message for f in fragments), message


def test_plot_runs_never_writes_its_curves_over_a_file_it_did_not_write(tmp_path, run, capsys):
    """`data=` X wrote the curves over any X (a run's summary.json, a user's notes): only the CLI refused it."""
    mine = copy(run, tmp_path / "r")
    notes = tmp_path / "notes.json"
    notes.write_text('{"my": "notes"}')
    before, notes_before = digest(mine), notes.read_bytes()
    for x in (mine / "summary.json", mine / "config.json", notes, tmp_path / "r" / "metrics"):
        with pytest.raises(ValueError) as e:
            plot_runs(mine, tmp_path / "c.png", data=x)
        one_line(e, f"--json {str(x)!r} exists and is not curves plot wrote", "pass another --json")
    assert digest(mine) == before and notes.read_bytes() == notes_before and not (tmp_path / "c.png").exists()
    refused(capsys, ["plot", mine, "--out", tmp_path / "c.png", "--json", notes],  # the CLI: the library's check
            "notes.json' exists and is not curves plot wrote")
    assert notes.read_bytes() == notes_before and not (tmp_path / "c.png").exists()
    plot_runs(mine, tmp_path / "c.png", data=tmp_path / "c.json")
    plot_runs(mine, tmp_path / "c.png", data=tmp_path / "c.json")  # its own curves: written over
    assert set(json.loads((tmp_path / "c.json").read_text())) == {"column", "curves"}


@pytest.mark.parametrize("call, error", [
    (lambda run, out: render_episode(run, out / "e.gif", greedy="no", max_steps=2), RenderError),
    (lambda run, out: evaluate(run, out=out / "ev", save="no", episodes=1), EvalError),
    (lambda run, out: plot_runs(run, out / "c.png", best="no"), ValueError),
    (lambda run, out: gap_report("tmaze_5", sweep="no", out=out / "g"), ConfigError),
    (lambda run, out: gap_report("tmaze_5", progress=1, out=out / "g"), ConfigError),
    (lambda run, out: run_benchmark(("tmaze_5",), out=out / "b", dry_run="no"), BenchmarkError),
    (lambda run, out: run_benchmark(("tmaze_5",), out=out / "b", dry_run=True, progress=None), BenchmarkError)])
def test_a_flag_that_is_not_a_bool_is_refused_not_read_as_true(tmp_path, run, call, error):
    with pytest.raises(error) as e:
        call(run, tmp_path)
    one_line(e, "must be True or False, got ")
    assert list(tmp_path.iterdir()) == []
    assert run_benchmark(("tmaze_5",), out=tmp_path / "b", dry_run=np.bool_(True), progress=False)["plan"]


def test_paths_expand_the_home_directory_and_empty_or_non_paths_are_refused(tmp_path, run, monkeypatch, capsys):
    """`~/x` was a literal ./~/x (train created it); "" wrote into the current directory; numbers and None were
    pathlib's TypeError."""
    home, cwd = tmp_path / "home", tmp_path / "cwd"
    home.mkdir(), cwd.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(cwd)
    copy(run, home / "r")

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop(args)

    with pytest.raises(Stop) as e:  # (stopped once the run directory is made: nothing trains)
        train(CFG, "~/t", progress=False, on_start=stop)
    assert e.value.args[0] == (home / "t",)
    assert load_run("~/r").path == home / "r"
    assert evaluate("~/r", out="~/ev", episodes=1).files[0].parent == home / "ev"
    assert render_episode("~/r", "~/e.gif", max_steps=2).gif == home / "e.gif" and (home / "e.png").exists()
    assert plot_runs("~/r", "~/c.png", data="~/c.json") == home / "c.png" and (home / "c.json").exists()
    monkeypatch.setattr(gap, "train_or_reuse", stop)
    with pytest.raises(Stop) as e:
        gap_report("tmaze_5", agents=("gru",), out="~/g", progress=False)
    assert e.value.args[0][1] == home / "g" / "gru"
    run_benchmark(("tmaze_5",), out="~/b", dry_run=True)
    assert f"into {home / 'b'}:" in capsys.readouterr().out
    assert list(cwd.iterdir()) == []  # no literal ~ anywhere, nothing in the current directory
    for call, error, fragment in [
            (lambda: evaluate("~/r", out="", episodes=1), EvalError, "out must be a directory path"),
            (lambda: evaluate("~/r", out=123, episodes=1), EvalError, "got 123"),
            (lambda: render_episode("~/r", out=123), RenderError, "out must be a file path"),
            (lambda: render_episode("~/r", out=""), RenderError, "got ''"),
            (lambda: load_run(5), RunLoadError, "load_run: path must be a run directory's path (a str or Path)"),
            (lambda: load_run(""), RunLoadError, "got ''"),
            (lambda: run_benchmark(("tmaze_5",), out=None, dry_run=True), BenchmarkError, "got None"),
            (lambda: run_benchmark(("tmaze_5",), out="", dry_run=True), BenchmarkError, "out must be a directory"),
            (lambda: gap_report("tmaze_5", out=""), ConfigError, "gap_report: out must be a directory path")]:
        with pytest.raises(error) as e:
            call()
        one_line(e, fragment)
    assert list(cwd.iterdir()) == []


def test_runs_started_within_one_second_get_default_directories_of_their_own(tmp_path, monkeypatch):
    """`for s in ...: train(replace(cfg, seed=s))` failed with RunDirExistsError on the second run's default
    directory (named to the second)."""
    monkeypatch.chdir(tmp_path)

    class Frozen(run_module.datetime.datetime):  # every run starts within the same second
        @classmethod
        def now(cls, tz=None):
            return cls(2025, 1, 2, 3, 4, 5)

    monkeypatch.setattr(run_module, "datetime", types.SimpleNamespace(datetime=Frozen))
    made = [train(dataclasses.replace(CFG, seed=s), progress=False, max_chunks=np.int64(1)).run_dir for s in range(2)]
    name = "tmaze_5-partial-gru-20250102-030405"
    assert made == [run_module.Path("runs") / name, run_module.Path("runs") / f"{name}-2"]
    assert all((p / "checkpoint.json").exists() for p in made)
    (tmp_path / "runs" / f"{name}-3").write_text("a file in the way")
    assert run_module.default_out(CFG) == run_module.Path("runs") / f"{name}-4"


@pytest.mark.parametrize("max_chunks", [float("nan"), True, "2", 1.5, 0, -1, np.int64(0)])
def test_max_chunks_other_than_a_positive_integer_is_refused_before_anything_is_made(tmp_path, max_chunks):
    """nan was ignored (every chunk trained), True counted as 1, "2" and 1.5 were a TypeError from a comparison."""
    with pytest.raises(ConfigError) as e:
        train(CFG, tmp_path / "r", progress=False, max_chunks=max_chunks)
    one_line(e, "--max-chunks must be a positive integer, or None", f"got {max_chunks!r}")
    assert list(tmp_path.iterdir()) == []


def test_a_single_string_for_a_tuple_of_names_is_refused_not_read_by_characters(tmp_path, monkeypatch):
    """envs="tmaze_5" was "Unknown environment 't'", a --merge "/x" "'/' has no benchmark.json", loggers="wandb"
    "Unknown logger 'w'"."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(BenchmarkError) as e:
        run_benchmark("tmaze_5", out=tmp_path / "b", dry_run=True)
    one_line(e, "envs is a tuple (or list) of names", "pass envs=('tmaze_5',)")
    with pytest.raises(BenchmarkError) as e:
        merge_results(tmp_path / "m", str(tmp_path / "b"))
    one_line(e, "sources is a tuple (or list) of directories", f"pass sources=({str(tmp_path / 'b')!r},)")
    with pytest.raises(ConfigError) as e:
        train(CFG, tmp_path / "r", progress=False, loggers="wandb")
    one_line(e, "loggers is a tuple (or list) of names", "pass loggers=('wandb',)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("call, fragment", [
    (lambda out: run_benchmark(("tmaze_5",), out=out / "b", dry_run=True, jobs="2"), "--jobs must be at least 1"),
    (lambda out: run_benchmark(("tmaze_5",), out=out / "b", dry_run=True, jobs=1.5), "got 1.5"),
    (lambda out: run_benchmark(("tmaze_5",), out=out / "b", dry_run=True, jobs=True), "got True"),
    (lambda out: run_benchmark(("tmaze_5",), out=out / "b", dry_run=True, jobs=0), "got 0"),
    (lambda out: gap_report("tmaze_5", sweep_seeds="5", out=out / "g"), "--sweep-seeds must be a positive integer"),
    (lambda out: gap_report("tmaze_5", sweep=True, sweep_seeds=2.5, out=out / "g"), "got 2.5"),
    (lambda out: gap_report("tmaze_5", sweep=True, sweep_seeds=True, out=out / "g"), "got True")])
def test_counts_other_than_positive_integers_are_refused(tmp_path, call, fragment):
    with pytest.raises((BenchmarkError, ConfigError)) as e:
        call(tmp_path)
    one_line(e, fragment)
    assert list(tmp_path.iterdir()) == []
    run_benchmark(("tmaze_5",), out=tmp_path / "b", dry_run=True, progress=False, jobs=np.int64(1))


@pytest.mark.parametrize("fps", [0, -1, 1e-6, float("nan"), float("inf"), "4", None, True, 1000])
def test_render_refuses_a_frame_rate_a_gif_cannot_hold_before_the_episode_plays(tmp_path, run, monkeypatch, fps):
    """0, -1, 1e-6, nan or "4" failed only once the episode had played (ZeroDivisionError, PIL's OverflowError)."""
    monkeypatch.setattr(animation, "record_episode", lambda *a, **k: pytest.fail("the episode played"))
    with pytest.raises(RenderError) as e:
        render_episode(run, tmp_path / "e.gif", fps=fps)
    one_line(e, "fps must be a number from 0.1 to 100", f"got {fps!r}")
    assert list(tmp_path.iterdir()) == []


def test_the_frame_rates_accepted_are_those_a_gif_holds(tmp_path):
    frames = [np.zeros((4, 4, 3), np.uint8), np.full((4, 4, 3), 255, np.uint8)]
    for fps, ms in ((0.1, 10000), (100, 10), (np.float32(4), 250)):
        with Image.open(animation.save_gif(frames, tmp_path / "x.gif", fps)) as gif:
            assert gif.info["duration"] == ms


def test_gap_reports_base_fields_win_over_the_preset(tmp_path, monkeypatch):
    """gap_report(base=TrainConfig(total_steps=2048, hidden_size=8, lr=0.01)) trained the registry's preset
    (1,000,000 steps, hidden size 32, lr 0.0025): the fields base sets were silently replaced."""
    gru = gap.gap_agents("tmaze_5", ("gru",))[0]
    base = TrainConfig(total_steps=2048, hidden_size=8, lr=0.01, num_seeds=1)
    preset = gap.agent_config("tmaze_5", gru)
    cfg = gap.agent_config("tmaze_5", gru, base, {})
    assert (cfg.total_steps, cfg.hidden_size, cfg.lr, cfg.num_seeds) == (2048, 8, (0.01,), 1)
    assert (preset.total_steps, preset.hidden_size) != (2048, 8)
    assert cfg.lambda0 == preset.lambda0 and cfg.num_envs == preset.num_envs  # what base leaves at its default
    assert gap.agent_config("tmaze_5", gru, base, {"lr": 0.5}).lr == (0.5,)  # overrides win over base
    assert gap.agent_config("tmaze_5", gru, dataclasses.replace(base, env="tmaze_5")).total_steps == 2048
    with pytest.raises(ValueError) as e:
        gap.agent_config("tmaze_5", gru, dataclasses.replace(base, memory="lstm"))
    one_line(e, "memory is set per agent by the gap report", "not overrides (or base)")
    with pytest.raises(ConfigError) as e:
        gap.agent_config("tmaze_5", gru, dataclasses.replace(base, env="tmaze_3"))
    one_line(e, "base.env 'tmaze_3' is not the report's environment 'tmaze_5'")
    with pytest.raises(ConfigError) as e:
        gap_report("tmaze_5", base={"total_steps": 2048}, out=tmp_path / "g")
    one_line(e, "base must be a TrainConfig or None, got a dict")
    assert list(tmp_path.iterdir()) == []
    trained = []

    class Stop(Exception):
        pass

    def record(cfg, path, *args, **kwargs):
        trained.append(cfg)
        raise Stop  # (nothing trains)

    monkeypatch.setattr(gap, "train_or_reuse", record)
    with pytest.raises(Stop):
        gap_report("tmaze_5", agents=("gru",), base=base, overrides={"seed": 7}, out=tmp_path / "g", progress=False)
    assert [(c.total_steps, c.hidden_size, c.lr, c.num_seeds, c.seed) for c in trained] == [(2048, 8, (0.01,), 1, 7)]
    assert gap_report.__doc__.count("base") >= 2
    assert os.path.isdir(tmp_path / "g")  # (claimed as the report's before training, as before)


def test_a_callback_that_is_not_a_function_is_refused_before_training(tmp_path):
    """on_chunk=5 trained the first chunk, then raised "'int' object is not callable"."""
    import pobax
    from pobax.agent import ConfigError

    for name in ("on_start", "on_chunk"):
        with pytest.raises(ConfigError, match=f"train: {name} must be a function"):
            pobax.train(CFG, tmp_path / name, progress=False, **{name: 5})
        assert not (tmp_path / name).exists()


def test_paper_preset_names_an_observability_the_environment_lacks():
    """paper_preset("tmaze_5", "gru", "fully") returned the ceiling's preset: any name but "partial" read as full."""
    from pobax.agent import ConfigError, paper_preset

    with pytest.raises(ConfigError, match="tmaze_5 has no observability 'fully'; choose among partial, full"):
        paper_preset("tmaze_5", "gru", "fully")
    assert paper_preset("tmaze_10", "memoryless", "full") != paper_preset("tmaze_10", "memoryless", "partial")
