"""Readers (`eval`, `plot`, `render`, `results`, `load_run`) beside another process that writes the same directory:
a trainer finishing the run they read, a resume starting on the run they write into, another render of the same
file. Each race is made deterministic by doing, in this process, what the other process does between two of the
reader's steps (the files it writes, in its order). Tiny T-Maze 5 runs on the CPU (`_hostile.py`)."""

import os

import pandas as pd
import pytest
from PIL import Image

import cli
from pobax.eval import RunDir, RunLoadError, evaluate, load_run
from pobax.eval._animation import render_episode

from _hostile import copy, refused


def _finish(run, finished):
    """What the trainer of `run` writes after its last chunk, in its order (`pobax.eval._run.train`): the chunk, the
    metrics table, the timing, the model, the sessions, the sealed summary; then its checkpoint cleared."""
    for chunk in sorted((finished / "metrics").iterdir()):
        (run / "metrics" / chunk.name).write_bytes(chunk.read_bytes())
    for name in ("metrics.csv", "timing.csv", "model.eqx", "sessions.json", "summary.json"):
        (run / name).write_bytes((finished / name).read_bytes())
    RunDir(run).clear_checkpoint()


def _finishing_after(monkeypatch, method: str, finished):
    """The trainer finishes the run right after the reader's `RunDir.method` returns (once)."""
    original, done = getattr(RunDir, method), []

    def then_finished(self, *args, **kwargs):
        result = original(self, *args, **kwargs)
        if not done:
            done.append(True)
            _finish(self.path, finished)
        return result

    monkeypatch.setattr(RunDir, method, then_finished)
    return done


@pytest.mark.parametrize("method", ["checkpoint_bytes", "check_unfinished"])
def test_a_run_that_finishes_while_load_run_reads_it_is_read_finished_through_its_seal(tmp_path, stopped, finished,
                                                                                         monkeypatch, method):
    """The trainer clears its checkpoint just after the reader checked it: load_run raised FileNotFoundError
    (checkpoint.json, read again for its manifest) instead of a RunLoadError or the finished run; a little later,
    it read model.eqx but returned a summary recomputed from the metrics, not the run's sealed summary.json."""
    run = copy(stopped, tmp_path / "run")
    done = _finishing_after(monkeypatch, method, finished)
    loaded = load_run(run)
    assert done
    assert loaded.finished and loaded.source == "model.eqx"
    assert loaded.summary.keys() == RunDir(finished).read_summary().keys()  # summary.json's, not one recomputed
    assert loaded.summary["finished"] is True and "sessions" in loaded.summary


@pytest.mark.parametrize("method", ["checkpoint_bytes", "check_unfinished"])
def test_metrics_of_a_run_that_finishes_while_read_are_its_sealed_metrics_table(tmp_path, stopped, finished,
                                                                                monkeypatch, method):
    """`plot` and `results` read the metrics (`RunDir.metrics`): a run that finished between the check of its
    checkpoint and its read raised FileNotFoundError (plot: "a folder on the path was removed") or was read from its
    chunks' files, unsealed and in another order, instead of its sealed metrics.csv."""
    run = copy(stopped, tmp_path / "run")
    done = _finishing_after(monkeypatch, method, finished)
    metrics = RunDir(run).metrics()
    assert done
    pd.testing.assert_frame_equal(metrics, pd.read_csv(finished / "metrics.csv"))


@pytest.mark.parametrize("command", ["plot", "eval"])
def test_plot_and_eval_of_a_run_that_finishes_meanwhile_read_it_finished(tmp_path, stopped, finished, monkeypatch,
                                                                         capsys, command):
    """The command line of the race above: exit 2 with "[Errno 2] No such file or directory: .../checkpoint.json; a
    folder on the path was removed", for a run that is whole."""
    run = copy(stopped, tmp_path / "run")
    done = _finishing_after(monkeypatch, "checkpoint_bytes", finished)
    args = ["plot", run, "--out", tmp_path / "c.png"] if command == "plot" else ["eval", run, "--episodes", "2"]
    cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert done and "Traceback" not in err and "error" not in err, err
    if command == "plot":
        assert (tmp_path / "c.png").read_bytes().startswith(b"\x89PNG")
    else:
        assert "model: model.eqx" in out and (run / "eval-partial-stochastic-seed0.json").is_file(), out


def test_a_resume_starting_keeps_the_temporaries_of_an_eval_writing_into_the_run(tmp_path, stopped, monkeypatch):
    """`train --resume RUN` removes the temporaries a killed trainer left in RUN when it starts; it removed every
    `.*.tmp`, so an `eval RUN` (or `plot`/`render` with --out in RUN) writing its file at that moment lost its
    temporary: OSError "No such file or directory" and no evaluation written. Only training's own are removed."""
    run = copy(stopped, tmp_path / "run")
    strays = [run / ".checkpoint-00004.eqx.0123456789ab.tmp", run / "metrics" / ".00003.csv.0123456789ab.tmp",
              run / ".checkpoint.json.ba9876543210.tmp"]
    for p in strays:  # a trainer killed in the middle of its writes
        p.write_bytes(b"half")
    replace, starts = os.replace, []

    def resume_starts_meanwhile(src, dst, *args, **kwargs):  # between the eval's temporary and its rename
        if os.path.basename(dst).startswith("eval-") and not starts:
            starts.append(True)
            RunDir(run).remove_stray_temporaries()  # what `train(..., resume=True)` does first, holding the run
        return replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", resume_starts_meanwhile)
    result = evaluate(run, episodes=2)
    assert starts and all(p.is_file() for p in result.files), result.files
    assert not any(p.exists() for p in strays)  # the killed trainer's are still removed


def _gif(path, color):
    Image.new("RGB", (4, 4), color).save(path, format="GIF")
    return path.read_bytes()


def _whole(path, earlier: bytes) -> bool:
    """Whether `path` holds the earlier image or a whole new one (not an empty or half-written file)."""
    if path.read_bytes() == earlier:
        return True
    try:
        with Image.open(path) as im:
            for frame in range(getattr(im, "n_frames", 1)):
                im.seek(frame)
                im.load()
    except Exception:  # noqa: BLE001
        return False
    return True


def test_render_writes_its_gif_and_strip_whole_and_replaces_a_link(tmp_path, finished, monkeypatch):
    """`render` wrote its GIF and strip in place (PIL and matplotlib open the path itself): while it wrote, another
    `render` of the same --out (checking that the file is a GIF before writing over it) or a viewer found an empty or
    half-written file, an interrupted render left one, and a link at --out was written through to the file it names.
    They are written whole, and a link is replaced, as `plot`'s figures are."""
    out, kept = tmp_path / "ep.gif", tmp_path / "kept.gif"
    earlier = {out: _gif(out, "red"), out.with_suffix(".png"): None}
    Image.new("RGB", (4, 4), "blue").save(out.with_suffix(".png"), format="PNG")
    earlier[out.with_suffix(".png")] = out.with_suffix(".png").read_bytes()
    seen = []
    Image.init()
    for registry, kind in ((Image.SAVE_ALL, "GIF"), (Image.SAVE, "PNG")):
        encode = registry[kind]

        def looking(im, fp, filename, _encode=encode):  # what a reader of --out finds while the image is encoded
            seen.extend(_whole(p, earlier[p]) for p in earlier)
            return _encode(im, fp, filename)

        monkeypatch.setitem(registry, kind, looking)
    r = render_episode(finished, out, max_steps=3)
    assert seen and all(seen), seen
    assert r.gif.read_bytes().startswith(b"GIF8") and r.png.read_bytes().startswith(b"\x89PNG")
    monkeypatch.undo()

    link = tmp_path / "link.gif"
    before = _gif(kept, "green")
    link.symlink_to(kept)
    render_episode(finished, link, max_steps=3)
    assert kept.read_bytes() == before and not link.is_symlink() and link.read_bytes().startswith(b"GIF8")


def test_plot_of_a_run_before_its_first_chunk_says_so(tmp_path, stopped, capsys):
    """`plot RUN` while another process has just started training RUN (its config.json written, no chunk yet) said
    "No metrics in RUN: is it a pobax run directory?" of a run directory; it says that no chunk is trained yet."""
    run = tmp_path / "run"
    (run / "metrics").mkdir(parents=True)
    (run / "config.json").write_bytes((stopped / "config.json").read_bytes())
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], "holds no metrics yet: its first chunk is not trained")
    assert not (tmp_path / "c.png").exists()


def test_a_finished_runs_summary_holding_null_is_refused_not_recomputed(tmp_path, finished):
    """summary.json holding `null` (no seal to check: not an object) read as "no summary read yet": load_run
    recomputed a summary from the metrics and reported the run as whole (and, once a run that finishes while it is
    read is read again, it would have read it again forever). It is refused, naming the file."""
    run = copy(finished, tmp_path / "run")
    (run / "summary.json").write_text("null\n")
    with pytest.raises(RunLoadError, match="summary.json' is not a summary pobax wrote"):
        load_run(run)


def test_results_skips_a_run_its_trainer_discards_while_it_is_listed(tmp_path, stopped, monkeypatch):
    """A `train` that fails before its first chunk (Ctrl-C while it compiles, a refused memory cell) removes the run
    directory it created (`RunDir.discard`): `results` that had just seen its config.json raised FileNotFoundError
    (exit 2, "a folder on the path was removed") instead of listing the other runs."""
    from pobax.eval import _listing

    copy(stopped, tmp_path / "kept")
    gone = tmp_path / "starting"
    (gone / "metrics").mkdir(parents=True)
    (gone / "config.json").write_bytes((stopped / "config.json").read_bytes())
    looked = _listing._is_run_config

    def then_discarded(path):
        answer = looked(path)
        if path.parent == gone:
            RunDir(gone).discard()  # what the failing trainer does now
        return answer

    monkeypatch.setattr(_listing, "_is_run_config", then_discarded)
    rows = _listing.list_runs(tmp_path)
    assert [r["path"] for r in rows] == [str(tmp_path / "kept")] and rows[0]["state"] == "resumable", rows


def test_a_finished_run_without_its_model_beside_a_damaged_checkpoint_is_refused_not_read_again(tmp_path, finished):
    """A run killed between its summary and clearing its checkpoint, then its model.eqx deleted and its
    checkpoint.json damaged: "finished while read" (summary.json there, the checkpoint unreadable) sent load_run into
    reading it again without end (RecursionError). Only the run's end, a summary and a model, reads it again."""
    run = copy(finished, tmp_path / "run")
    (run / "model.eqx").unlink()
    (run / "checkpoint.json").write_text("{}")
    with pytest.raises(RunLoadError, match="checkpoint"):
        load_run(run)
