"""Files that are not what a command expects: a FIFO where a run's file or a preset should be (reading one waits for
a writer that never comes), a strip that would overwrite a file render did not write, a run another process
trains, and memory inputs of the wrong shape or type. Tiny T-Maze 5 runs on the CPU (`_hostile.py`)."""

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

import cli
from pobax.eval import RunDir
from pobax.eval._listing import list_runs
from pobax.memory import MEMORIES

from _hostile import TINY, copy, digest, refused

fifo_only = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs (POSIX)")


@fifo_only
@pytest.mark.parametrize("name", ["metrics.csv", "summary.json", "model.eqx"])
def test_a_fifo_in_a_finished_run_is_refused_not_waited_on(tmp_path, finished, capsys, name):
    """eval, plot and results read a FIFO put where a run's file was, and waited for a writer forever."""
    run = copy(finished, tmp_path / "r")
    (run / name).unlink()
    os.mkfifo(run / name)
    before = digest(run)
    refused(capsys, ["eval", run, "--episodes", "2"], name, "not a regular file")
    if name != "model.eqx":  # (plot reads no model)
        refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], name, "not a regular file")
    [row] = list_runs(tmp_path)
    assert row["state"] == "damaged" and "not a regular file" in row["problem"], row
    assert digest(run) == before and not (tmp_path / "c.png").exists()


def test_results_names_a_finished_run_whose_model_is_gone(tmp_path, finished, capsys):
    """`results` listed a finished run without its model.eqx as finished, while eval refuses it
    (test_hostile_inputs): it is damaged, with eval's reason."""
    run = copy(finished, tmp_path / "r")
    (run / "model.eqx").unlink()
    [row] = list_runs(tmp_path)
    assert row["state"] == "damaged" and "is a finished run without its model.eqx" in row["problem"], row
    cli.main(["results", "--root", str(tmp_path)])
    assert "is a finished run without its model.eqx" in capsys.readouterr().err


@fifo_only
def test_a_preset_that_is_a_fifo_is_refused(tmp_path, capsys):
    os.mkfifo(tmp_path / "best.json")
    refused(capsys, ["train", *TINY, "--preset", tmp_path / "best.json", "--out", tmp_path / "run"],
            "is not a regular file")
    assert not (tmp_path / "run").exists()


@fifo_only
def test_a_fifo_for_a_benchmarks_lock_or_figure_is_named_before_training(tmp_path, capsys):
    """A FIFO at .benchmark.lock ended `benchmark` in "File or stream is not seekable"; one at benchmark.png was
    named inside a second, nested message."""
    from pobax.eval._files import check_figure_path

    os.mkfifo(tmp_path / ".benchmark.lock")
    with pytest.raises(SystemExit) as e:
        cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1, err
    assert ".benchmark.lock' is not a regular file (a FIFO, device or socket)" in err and "remove it" in err, err
    assert [p.name for p in tmp_path.iterdir()] == [".benchmark.lock"]
    os.mkfifo(tmp_path / "benchmark.png")
    with pytest.raises(FileExistsError, match=r"^the figure '.*benchmark.png' is not a regular file \(a FIFO, device "
                       r"or socket\), so not a file pobax wrote: name another file, or move it aside.$"):
        check_figure_path(tmp_path / "benchmark.png", "the figure")


def test_a_preset_that_is_a_looping_link_is_named(tmp_path, capsys):
    """A preset file linked to itself was reported as a file that "does not exist"."""
    (tmp_path / "best.json").symlink_to(tmp_path / "best.json")
    refused(capsys, ["train", *TINY, "--preset", tmp_path / "best.json", "--out", tmp_path / "run"],
            "is a symbolic link that leads to nothing or back to itself")
    assert not (tmp_path / "run").exists()


def test_render_does_not_write_its_strip_over_a_file_it_did_not_write(tmp_path, finished, capsys):
    """`render --out x.gif` also writes x.png: it wrote over a user's x.png (a results figure, say)."""
    theirs = tmp_path / "figure.png"
    theirs.write_bytes(b"not render's")
    refused(capsys, ["render", finished, "--out", tmp_path / "figure.gif"],
            "figure.png', which exists and is not the strip")
    assert theirs.read_bytes() == b"not render's" and not (tmp_path / "figure.gif").exists()
    for _ in range(2):  # render's own strip, beside its own .gif, is rewritten
        cli.main(["render", str(finished), "--out", str(tmp_path / "episode.gif")])
    assert (tmp_path / "episode.gif").stat().st_size > 0 and (tmp_path / "episode.png").stat().st_size > 0


def test_results_shows_a_run_another_process_trains(tmp_path, stopped):
    """`results` listed a run being trained as resumable: resuming it would be refused (the trainer holds it)."""
    run = copy(stopped, tmp_path / "r")
    assert [r["state"] for r in list_runs(tmp_path)] == ["resumable"]
    trainer = RunDir(run)
    trainer.hold()  # as `train` holds its run directory (a lock on another open file: as another process's)
    try:
        assert [r["state"] for r in list_runs(tmp_path)] == ["training"]
    finally:
        trainer.release()
    assert [r["state"] for r in list_runs(tmp_path)] == ["resumable"]  # the probe took nothing away
    RunDir(run).hold()  # and left the lock free


def test_every_memory_refuses_starts_of_another_shape_or_type():
    """One cell broadcast a (time, 1) `starts`, another read floats as starts, S6 failed in a type check deep inside
    memax, the memoryless cell took anything: every built-in cell now says what the contract wants. Run as a user
    runs it, without the test suite's jaxtyping hook (which refuses such calls before the cell sees them)."""
    script = textwrap.dedent("""
        import equinox as eqx, jax, jax.numpy as jnp
        from pobax.memory import MEMORIES, memory_class
        for memory in MEMORIES:  # shapes only (`filter_eval_shape`): the check is on shapes and dtypes
            cls = memory_class(memory)
            args = (3,) if memory == "trxl" else (3, 8)
            cell = eqx.filter_eval_shape(lambda: cls(*args, key=jax.random.key(0)))
            carry, xs = eqx.filter_eval_shape(cell.init_carry), jnp.ones((6, 3))
            bad = [(xs, s) for s in (jnp.zeros((6, 1), bool), jnp.zeros(6), jnp.zeros(6, jnp.int32),
                                     jnp.zeros(5, bool), [False] * 6)] + [(jnp.ones((6, 4)), jnp.zeros(6, bool))]
            for x, s in bad:
                try:
                    eqx.filter_eval_shape(cell, carry, x, s)
                except ValueError as e:
                    print(memory, str(e).split(": ", 1)[1].split(";")[0])
                else:
                    print(memory, "accepted")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    lines = out.stdout.splitlines()
    assert out.returncode == 0 and len(lines) == 6 * len(MEMORIES), out.stderr[-2000:]
    for memory in MEMORIES:
        said = [line.split(" ", 1)[1] for line in lines if line.split(" ", 1)[0] == memory]
        assert said[:5] == [f"starts must be a bool array of shape (time,) = (6,), got {got}" for got in
                            ("bool (6, 1)", "float32 (6,)", "int32 (6,)", "bool (5,)", "list")], (memory, said)
        assert said[5] == "xs must be an array of shape (time >= 1, 3), got (6, 4)", (memory, said)


def test_figures_are_not_written_over_a_file_that_is_not_such_an_image(tmp_path, finished, capsys):
    """`plot --out mine.png` and `render --out ep.gif` wrote over whatever file had that name (a copy of a README, a
    note); an image of the name's format, an earlier figure, is still written over, so plotting again works."""
    from pobax.eval import plot_runs

    for name in ("mine.png", "ep.gif", "notes.pdf"):
        (tmp_path / name).write_text("the user's words\n")
    refused(capsys, ["plot", finished, "--out", tmp_path / "mine.png"], "mine.png' exists and is not a PNG image")
    refused(capsys, ["plot", finished, "--out", tmp_path / "notes.pdf"], "is not a PDF image")
    refused(capsys, ["render", finished, "--out", tmp_path / "ep.gif"], "ep.gif' exists and is not a GIF image")
    with pytest.raises(FileExistsError, match="not a PNG image"):
        plot_runs(finished, tmp_path / "mine.png")
    assert all((tmp_path / n).read_text() == "the user's words\n" for n in ("mine.png", "ep.gif", "notes.pdf"))
    assert not (tmp_path / "ep.png").exists()
    for _ in range(2):  # pobax's own figure, plotted again
        cli.main(["plot", str(finished), "--out", str(tmp_path / "curves.png")])
    assert (tmp_path / "curves.png").read_bytes().startswith(b"\x89PNG")


def test_an_empty_path_or_name_is_refused_not_read_as_the_current_directory(tmp_path, finished, capsys, monkeypatch):
    """`--out "$DIR"` with DIR unset trained into the current directory; `plot --metric ""` plotted the default."""
    monkeypatch.chdir(tmp_path)
    refused(capsys, ["train", *TINY, "--out", ""], "--out is empty: give it a value")
    refused(capsys, ["train", *TINY, "--out="], "--out is empty")
    refused(capsys, ["eval", ""], "an argument is empty")
    refused(capsys, ["plot", finished, "--metric", ""], "--metric is empty")
    assert os.listdir(tmp_path) == []


def test_a_name_too_long_for_the_file_system_says_what_to_do(tmp_path, finished, capsys):
    refused(capsys, ["plot", finished, "--out", tmp_path / ("a" * 300 + ".png")], "File name too long",
            "pass a shorter path")


def test_an_out_that_is_a_dangling_or_looping_link_is_named_as_one(tmp_path, capsys):
    """A dangling `--out` link was refused as "(File exists)", which it does not."""
    os.symlink("nowhere", tmp_path / "dangling")
    os.symlink("loop", tmp_path / "loop")
    refused(capsys, ["train", *TINY, "--out", tmp_path / "dangling"], "a symbolic link to 'nowhere', which does not")
    refused(capsys, ["train", *TINY, "--out", tmp_path / "loop"], "a symbolic link to 'loop'")
    assert sorted(os.listdir(tmp_path)) == ["dangling", "loop"]


@pytest.mark.parametrize("name", ["config.json", "summary.json", "metrics.csv", "model.eqx"])
def test_a_file_of_a_finished_run_linked_to_nothing_is_named_as_such(tmp_path, finished, capsys, name):
    """A run's file replaced by a link to a file that does not exist read as the system's "[Errno 2] No such file"
    about the link itself, which is there."""
    run = copy(finished, tmp_path / "r")
    (run / name).unlink()
    os.symlink(tmp_path / "gone", run / name)
    said = f"{str(run / name)!r} is a symbolic link to {str(tmp_path / 'gone')!r}, which does not exist"
    refused(capsys, ["eval", run, "--episodes", "2"], said)
    if name in ("config.json", "metrics.csv"):  # (plot reads no model, and a run without a summary is in training)
        refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], said)
        assert not (tmp_path / "c.png").exists()
    if name == "config.json":
        refused(capsys, ["train", "--resume", run], said)
    [row] = list_runs(tmp_path)  # (a config.json linked to nothing was not found: "No runs")
    assert row["state"] == "damaged" and said in row["problem"], row


@pytest.mark.parametrize("event", ["moved", "removed", "replaced"])
def test_a_run_directory_moved_or_removed_while_training_stops_it(tmp_path, finished, capsys, event):
    """Moved during training, a run went on writing by its old path: its later chunks, checkpoint, model and summary
    into a new directory without its config.json, while the moved directory stopped short, the run split in two.
    Training stops now, says where the run is, and the moved run continues from there to the same metrics."""
    out, moved = tmp_path / "a", tmp_path / "b"

    def move(chunk):
        if chunk.index == 1:
            out.rename(moved)
            if event == "removed":
                shutil.rmtree(moved)
            if event == "replaced":
                out.mkdir()

    expected = {"moved": ["moved or replaced", f"it is now {str(moved)!r}", f"--resume {moved}"],
                "replaced": ["moved or replaced", f"--resume {moved}"],
                "removed": ["was removed while training", "train it again"]}[event]
    refused(capsys, ["train", *TINY, "--out", out], *expected, on_chunk=move)
    assert not out.exists() or not any(out.iterdir())  # nothing written at the old path
    if event != "removed":
        assert not (moved / "summary.json").exists()
        cli.main(["train", "--resume", str(moved), "--quiet"])
        assert (moved / "metrics.csv").read_bytes() == (finished / "metrics.csv").read_bytes()
