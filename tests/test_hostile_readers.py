"""The commands that read run directories (`eval`, `plot`, `results`) under a hostile user: a finished run's files
edited or deleted, outputs that name each other or files the command did not write. Tiny T-Maze 5 runs on the CPU
(`_hostile.py`)."""

import json

import pandas as pd
import pytest

import cli
from pobax.eval._listing import list_runs

from _hostile import TINY, copy, digest, refused


def _edit_config(run, **fields):
    record = json.loads((run / "config.json").read_text())
    for key, value in fields.items():
        if key in record["config"]:
            record["config"][key] = value
        else:
            record[key] = value
    (run / "config.json").write_text(json.dumps(record))


def test_a_finished_runs_edited_config_json_is_refused_by_eval_plot_and_results(tmp_path, finished, capsys):
    """eval played the T-Maze 5 agent on the environment an edit named, plot labelled its curve with a step size the
    run never trained at, results listed it under the edited environment: the seal now covers config.json."""
    for name, fields in (("env", {"env": "tmaze_3"}), ("lr", {"lr": [0.1], "hyperparameter_sets": [{"lr": 0.1}]}),
                         ("spec", {"env_spec": None})):
        run = copy(finished, tmp_path / name)
        _edit_config(run, **fields)
        before = digest(run)
        refused(capsys, ["eval", run, "--episodes", "2"], "config.json' differs from the configuration its run "
                "finished with")
        refused(capsys, ["plot", run, "--out", tmp_path / f"{name}.png"], "config.json' differs")
        assert digest(run) == before and not (tmp_path / f"{name}.png").exists()
    assert {r["state"] for r in list_runs(tmp_path)} == {"damaged"}


def test_a_finished_runs_deleted_metrics_table_is_not_replaced_by_its_chunks(tmp_path, finished, capsys):
    """With metrics.csv deleted, plot read the chunk files (unchecked: edited to 99) and drew them."""
    run = copy(finished, tmp_path / "r")
    (run / "metrics.csv").unlink()
    for chunk in sorted((run / "metrics").glob("*.csv")):
        pd.read_csv(chunk).assign(disc_return=99.0).to_csv(chunk, index=False)
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], "metrics.csv' is missing", "restore it")
    assert [r["state"] for r in list_runs(tmp_path)] == ["damaged"]


def test_an_unfinished_runs_damaged_reference_or_sets_are_no_traceback(tmp_path, stopped, capsys):
    run = copy(stopped, tmp_path / "r")
    _edit_config(run, env_spec={"reference": [1, 2]}, hyperparameter_sets=1)
    cli.main(["plot", str(run), "--out", str(tmp_path / "c.png")])
    cli.main(["eval", str(run), "--episodes", "2", "--out", str(tmp_path / "ev")])
    assert (tmp_path / "c.png").is_file() and len(list((tmp_path / "ev").glob("eval-*"))) == 2


def test_plot_json_onto_its_own_figure_is_refused(tmp_path, finished, capsys):
    refused(capsys, ["plot", finished, "--out", tmp_path / "c.png", "--json", tmp_path / "c.png"],
            "is the figure's own path")
    assert not (tmp_path / "c.png").exists()


@pytest.mark.slow
def test_plot_draws_every_run_of_one_label(tmp_path, capsys):
    """Three runs alike but for their directories (x/run, y/run, z/run): the second's curve was replaced by the
    third's, as both were labelled by the directory's last name."""
    runs = [tmp_path / d / "run" for d in "xyz"]
    for i, run in enumerate(runs):
        cli.main(["train", *TINY, "--total-steps", "1024", "--num-seeds", "1", "--seed", str(i), "--out", str(run)])
    cli.main(["plot", *map(str, runs), str(runs[0]), "--out", str(tmp_path / "c.png"), "--json",
              str(tmp_path / "c.json")])
    curves = json.loads((tmp_path / "c.json").read_text())["curves"]
    assert sorted(c["run_dir"] for c in curves.values()) == sorted(map(str, [*runs, runs[0]]))


@pytest.mark.slow
def test_eval_does_not_write_over_files_or_evaluations_it_did_not_write(tmp_path, finished, capsys):
    """A .csv of the user's was replaced when its .json was missing; the evaluation of another model in the same run
    directory (trained again there) was replaced as the run's path and `model.eqx` were all that identified it."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "eval-partial-stochastic-seed0.csv").write_text("my,own,data\n")
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", mine], "eval-partial-stochastic-seed0.csv' exists "
            "and is not an evaluation eval wrote")
    assert (mine / "eval-partial-stochastic-seed0.csv").read_text() == "my,own,data\n"
    run, small = tmp_path / "r", [*TINY, "--total-steps", "1024", "--num-seeds", "1"]
    cli.main(["train", *small, "--out", str(run)])
    cli.main(["eval", str(run), "--episodes", "2", "--out", str(tmp_path / "ev")])
    first = digest(tmp_path / "ev")
    run.rename(tmp_path / "aside")
    cli.main(["train", *small, "--memory", "memoryless", "--out", str(run)])
    capsys.readouterr()
    refused(capsys, ["eval", run, "--episodes", "2", "--out", tmp_path / "ev"], "other settings", "model_sha256")
    assert digest(tmp_path / "ev") == first


def test_eval_and_render_outputs_they_cannot_write_are_refused_before_playing(tmp_path, finished, capsys, monkeypatch):
    """A broken link or a read-only folder as --out: a bare `[Errno 17] File exists` or `[Errno 30] Read-only file
    system` after the episodes were played; now one line naming --out, before anything is played."""
    (tmp_path / "broken").symlink_to(tmp_path / "nowhere")
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", tmp_path / "broken"], "is a file or a broken link",
            "pass another --out")
    refused(capsys, ["render", finished, "--out", tmp_path / "broken" / "e.gif"], "is a file or a broken link")
    (tmp_path / "ro").mkdir()
    monkeypatch.setattr("os.access", lambda path, mode: str(path) != str(tmp_path / "ro"))  # (root writes anywhere)
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", tmp_path / "ro" / "ev"],
            f"--out {str(tmp_path / 'ro' / 'ev')!r} cannot be written ({str(tmp_path / 'ro')!r} is not writable)")
    refused(capsys, ["render", finished, "--out", tmp_path / "ro" / "e.gif"], "e.gif' cannot be written")
    # a folder os.access calls writable where nothing can be created (root's /proc): found by creating a file there
    refused(capsys, ["eval", finished, "--episodes", "2", "--out", "/proc/pobax-ev"], "'/proc/pobax-ev' cannot be "
            "written ('/proc' is not writable)")
    refused(capsys, ["render", finished, "--out", "/proc/pobax-e.gif"], "e.gif' cannot be written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "ro"] and not list((tmp_path / "ro").iterdir())


def test_an_unfinished_runs_edited_config_is_refused_by_readers_as_by_resume(tmp_path, stopped, capsys):
    """config.json of a stopped run edited (lr 2.5e-4 → 0.1): resume refused it, but plot drew and eval played it
    labelled lr=0.1, results listed it resumable. Readers now check what a resume checks (`check_unfinished`)."""
    from pobax.eval import RunLoadError, load_run

    run = copy(stopped, tmp_path / "r")
    _edit_config(run, lr=[0.1], hyperparameter_sets=[{"lr": 0.1}])
    before = digest(run)
    why = "config.json differs from the configuration the run started with in lr ([0.00025] → [0.1])"
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], why)
    refused(capsys, ["eval", run, "--episodes", "2", "--out", tmp_path / "ev"], why)
    refused(capsys, ["train", "--resume", run], why)
    with pytest.raises(RunLoadError, match="differs from the configuration the run started with"):
        load_run(run)
    [row] = list_runs(tmp_path)
    assert row["state"] == "damaged" and why in row["problem"]
    assert digest(run) == before and not (tmp_path / "c.png").exists() and not (tmp_path / "ev").exists()


def test_a_finished_run_without_its_summary_is_damaged_not_read_unchecked(tmp_path, finished, capsys):
    """summary.json (and with it the seal) deleted, metrics.csv edited (+5): plot and eval read the edited table and
    an unchecked model, results called it incomplete; only resume refused it."""
    run = copy(finished, tmp_path / "r")
    (run / "summary.json").unlink()
    pd.read_csv(run / "metrics.csv").assign(disc_return=5.0).to_csv(run / "metrics.csv", index=False)
    why = "has trained past a checkpoint (metrics.csv, model.eqx"
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], why, "no checkpoint.json (nor summary.json)")
    refused(capsys, ["eval", run, "--episodes", "2", "--out", tmp_path / "ev"], why)
    [row] = list_runs(tmp_path)
    assert row["state"] == "damaged" and why in row["problem"]


def test_listed_states_agree_with_resume_and_a_config_directory_is_named(tmp_path, stopped, finished, capsys):
    """Runs that resume refused were listed resumable (sessions.json deleted), and a finished run whose config.json
    was replaced by a directory vanished from the listing while eval said it had no config.json."""
    gone = copy(stopped, tmp_path / "sessions")
    (gone / "sessions.json").unlink()
    refused(capsys, ["train", "--resume", gone], "sessions.json' does not record the sessions")
    moved = copy(finished, tmp_path / "dir")
    (moved / "config.json").unlink()
    (moved / "config.json").mkdir()
    refused(capsys, ["eval", moved, "--episodes", "2"], "config.json' is a directory, not the configuration file")
    refused(capsys, ["train", "--resume", moved], "config.json' is a directory")
    rows = {r["path"]: r for r in list_runs(tmp_path)}
    assert rows[str(gone)]["state"] == "damaged" and "sessions.json" in rows[str(gone)]["problem"]
    assert rows[str(moved)]["state"] == "damaged" and "is a directory" in rows[str(moved)]["problem"]
    (tmp_path / "ok").mkdir()
    assert [r["state"] for r in list_runs(copy(stopped, tmp_path / "ok" / "r").parent)] == ["resumable"]


def test_a_stray_model_in_an_unfinished_run_is_not_read_as_its_trained_model(tmp_path, stopped, finished, capsys):
    """Another run's model.eqx copied into a stopped run (checkpoint, no summary): eval played it as the run's final
    model and load_run said finished, while results and resume treated the run as unfinished. Readers now read what a
    resume continues: the checkpoint."""
    from pobax.eval import load_run

    run = copy(stopped, tmp_path / "r")
    (run / "model.eqx").write_bytes((finished / "model.eqx").read_bytes())
    loaded = load_run(run)
    assert not loaded.finished and loaded.source == "checkpoint after chunk 3"
    assert [r["state"] for r in list_runs(tmp_path)] == ["resumable"]


@pytest.mark.parametrize("name, damage, message", [
    ("metrics.csv", "directory", "metrics.csv' is a directory, not the file pobax wrote there"),  # was [Errno 21]
    ("model.eqx", "directory", "model.eqx' is a directory"),  # results listed the run as finished
    ("metrics.csv", "loop", "metrics.csv' is a symbolic link that leads back to itself"),  # was "is missing"
    ("config.json", "loop", "config.json' is a symbolic link that leads back to itself")])  # "not a run directory"
def test_a_run_file_replaced_by_a_directory_or_a_looping_link_is_named(tmp_path, finished, capsys, name, damage,
                                                                        message):
    from pobax.eval import RunLoadError, load_run

    run = copy(finished, tmp_path / "r")
    (run / name).unlink()
    if damage == "directory":
        (run / name).mkdir()
    else:
        (run / name).symlink_to(run / name)
    refused(capsys, ["eval", run, "--episodes", "2", "--out", tmp_path / "ev"], message, "restore the file")
    with pytest.raises(RunLoadError, match=message.replace(".", r"\.")):
        load_run(run)
    assert [r["state"] for r in list_runs(tmp_path)] == ["damaged"]


def test_a_deleted_observation_normaliser_is_named_as_missing(tmp_path, capsys):
    """A finished --normalize-obs run without its obs_norm.eqx (sealed): eval blamed a run "finished before
    obs_norm.eqx existed" and gave no fix."""
    from pobax.eval import RunLoadError, load_run

    run = tmp_path / "r"
    cli.main(["train", *TINY, "--normalize-obs", "--out", str(run)])
    capsys.readouterr()
    (run / "obs_norm.eqx").unlink()
    refused(capsys, ["eval", run, "--episodes", "2"], "obs_norm.eqx' is missing: the run finished with it",
            "restore it")
    with pytest.raises(RunLoadError, match="obs_norm.eqx' is missing"):
        load_run(run)


def test_a_run_diverged_by_its_reward_scale_is_told_to_lower_it(tmp_path, capsys):
    """`--reward-scale 1e30`: every seed diverged, and eval's hint named only --lr."""
    run = tmp_path / "r"
    cli.main(["train", *TINY, "--reward-scale", "1e30", "--out", str(run)])
    capsys.readouterr()
    refused(capsys, ["eval", run, "--episodes", "2"], "diverged in training", "--reward-scale (it trained at 1e+30)")


def test_results_lists_a_linked_run_once_and_names_a_looping_link_in_a_sweep(tmp_path, finished):
    """A sweep's program directory replaced by a link to itself vanished from `results`; a run reached through a link
    to its directory was not listed at all (os.walk did not follow it), and a link to a folder above is no loop."""
    root = tmp_path / "root"
    (root / "sweep").mkdir(parents=True)
    (root / "sweep" / "pobax-sweep.json").write_text("{}")
    (root / "sweep" / "base").symlink_to(root / "sweep" / "base")
    (root / "linked").symlink_to(copy(finished, tmp_path / "elsewhere"))
    (root / "up").symlink_to(root)
    rows = list_runs(root)
    assert [(r["path"], r["state"]) for r in rows] == [(str(root / "linked"), "finished"),
                                                       (str(root / "sweep" / "base"), "damaged")]
    assert "is a symbolic link to" in rows[1]["problem"] and "leads back to itself" in rows[1]["problem"]
