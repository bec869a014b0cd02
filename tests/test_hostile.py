"""The README's "Runs are results or refusals", tried as a hostile but fair user would: two processes on one run
directory, edited or damaged run directories, malformed records, a killed benchmark, and every subcommand on what
that leaves. Tiny T-Maze 5 runs on the CPU (`_hostile.py`); bad input and numbers too large: `test_hostile_inputs.py`."""


import json
import shutil
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

import cli
from pobax.eval import RunDir, RunLoadError, load_run
from pobax.eval._locks import shared_files
from pobax.eval._plan import BenchmarkError, benchmark_dir
from pobax.eval._records import seal_record
from pobax.eval._report import write_results

from _hostile import CFG, ROOT, TINY, copy, digest, pre_seal, refused, unseal, write_summary


# --- 1. one process per run directory -------------------------------------------------------------------------

@pytest.mark.slow
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
    unseal(run)  # a run from before the seal (else a summary without one is refused first: its seal removed)
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
            err = refused(capsys, [a.format(run=run, tmp=tmp_path) for a in command], f"{str(run / 'config.json')!r}")
            assert "is not a run configuration pobax wrote" in err or (  # or a finished run's seal says it first
                src == finished and "differs from the configuration its run finished with" in err), err
        assert digest(run) == before
    assert not list(tmp_path.glob("c.png")) and not list(tmp_path.glob("e.*"))


def test_plot_labels_from_the_configuration_not_an_edited_list_of_sets(tmp_path, stopped, capsys):
    run = copy(stopped, tmp_path / "r")  # (a finished run's seal refuses the edit)
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
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], f"{str(run / 'metrics.csv')!r}",
            "differs from the file its run finished with")  # (its seal, checked first)
    with pytest.raises(ValueError, match="differs from the file its run finished with"):
        load_run(run)
    unseal(run)
    refused(capsys, ["plot", run, "--out", tmp_path / "c.png"], f"{str(run / 'metrics.csv')!r}", message)
    with pytest.raises(ValueError) as e:
        load_run(run)
    assert message in str(e.value)
    assert not (tmp_path / "c.png").exists()


def _edit_summary(run: Path) -> None:
    summary = json.loads((run / "summary.json").read_text())
    for block in (summary["sets"][0]["disc_return"], summary["sets"][0]["return"]):
        block.update(mean=99.0, ci_low=99.0, ci_high=99.0, per_seed=[99.0] * len(block["per_seed"]))
    (run / "summary.json").write_text(json.dumps(summary))  # its seal kept, as a hand edit keeps it


def _unseal_summary(run: Path) -> None:
    _edit_summary(run)
    summary = json.loads((run / "summary.json").read_text())
    (run / "summary.json").write_text(json.dumps({k: v for k, v in summary.items() if k != "sha256"}))  # the seal gone


def _edit_metrics(run: Path) -> None:
    text = (run / "metrics.csv").read_text()
    header, first, rest = text.split("\n", 2)
    row = first.split(",")
    col = header.split(",").index("disc_return")
    row[col] = "99.0"
    (run / "metrics.csv").write_text("\n".join([header, ",".join(row), rest]))


def _edit_model(run: Path) -> None:
    data = bytearray((run / "model.eqx").read_bytes())
    data[-1] ^= 1  # one bit of the last parameter
    (run / "model.eqx").write_bytes(bytes(data))


@pytest.mark.parametrize("edit, name, message", [
    (_edit_summary, "summary.json", "was edited after its run finished"),
    (_unseal_summary, "summary.json", "has no seal"),  # was read as a summary from before the seal
    (_edit_metrics, "metrics.csv", "differs from the file its run finished with"),
    (_edit_model, "model.eqx", "differs from the file its run finished with")])
def test_a_finished_run_edited_after_it_finished_is_refused_by_every_reader(tmp_path, finished, capsys, edit, name,
                                                                           message):
    """A finished run's summary.json, metrics.csv or model.eqx edited consistently (valid, of the right shape): a
    benchmark or sweep reusing it reported the edited returns (and a sweep selected by them), `results` listed them.
    The summary's seal (its own SHA-256 and its files') refuses it, naming the file, in every reader."""
    from pobax.eval._run import train_or_reuse

    root = tmp_path / "runs"
    root.mkdir()
    run, good = copy(finished, root / "a-edited"), copy(finished, root / "b-finished")
    edit(run)
    before = digest(root)
    with pytest.raises(ValueError, match=message):
        train_or_reuse(CFG, run, progress=False)  # what benchmark, sweep and gap reuse finished runs through
    with pytest.raises(ValueError, match=message):
        load_run(run)
    refused(capsys, ["eval", run, "--episodes", "2"], f"{str(run / name)!r}", message)
    cli.main(["results", "--root", str(root)])
    out, err = capsys.readouterr()
    rows = {line.split()[0]: line for line in out.splitlines()[1:]}
    assert " damaged " in rows[str(run)] and " finished " in rows[str(good)], out
    assert f"{str(run / name)!r}" in err and message in err, err
    assert digest(root) == before


@pytest.mark.parametrize("edit", [lambda s: {**s, "best_by_auc": -1},  # listed as finished (the last set)
                                  lambda s: {**s, "sets": [{**s["sets"][0], "disc_return": {
                                      **s["sets"][0]["disc_return"], "ci_low": [1]}}]},  # a TypeError, no list
                                  lambda s: {**s, "sets": [{**s["sets"][0], "disc_return": {
                                      **s["sets"][0]["disc_return"], "ci_high": "1.1"}}]}])  # a format error
def test_results_lists_a_run_whose_summary_has_another_shape_as_damaged(tmp_path, finished, capsys, edit):
    """Summaries of another shape, sealed as if pobax had written them: `results` stopped at the first (a traceback
    or an error naming no file, the runs after it never listed) or listed it as finished; it is damaged, named."""
    root = tmp_path / "runs"
    root.mkdir()
    run, good = copy(finished, root / "a-edited"), copy(finished, root / "b-finished")
    write_summary(run, edit(json.loads((run / "summary.json").read_text())))
    cli.main(["results", "--root", str(root)])
    out, err = capsys.readouterr()
    rows = {line.split()[0]: line for line in out.splitlines()[1:]}
    assert " damaged " in rows[str(run)] and " finished " in rows[str(good)], out
    assert f"{str(run / 'summary.json')!r} is not a run's summary pobax wrote" in err, err


def test_a_finished_runs_summary_json_linked_to_itself_is_named(tmp_path, finished, capsys):
    run = copy(finished, tmp_path / "r")
    (run / "summary.json").unlink()
    (run / "summary.json").symlink_to(run / "summary.json")  # `results`: "incomplete"; a resume: "no summary.json"
    refused(capsys, ["train", "--resume", run], "already finished (summary.json)")
    cli.main(["results", "--root", str(tmp_path)])
    out, err = capsys.readouterr()
    assert " damaged " in out and f"{str(run / 'summary.json')!r} is a symbolic link that leads back to itself" \
        in err, (out, err)
    # readers name the loop too (load_run raised OSError [Errno 40], plot said "no checkpoint.json (nor summary.json)")
    refused(capsys, ["plot", run, "--out", tmp_path / "p.png"], "summary.json' is a symbolic link that leads back")
    with pytest.raises(RunLoadError, match="summary.json' is a symbolic link that leads back to itself"):
        load_run(run)


@pytest.mark.parametrize("command", ["sweep", "gap"])
def test_a_damaged_marker_of_a_sweep_or_gap_out_is_refused_naming_it(tmp_path, capsys, command):
    out = tmp_path / "o"
    out.mkdir()
    mark = out / f"pobax-{command}.json"
    for text in ("[1]", '"x"'):  # was an AttributeError traceback
        mark.write_text(text)
        args = [*TINY, "--lr", "1e-3", "1e-4"] if command == "sweep" else ["--env", "tmaze_5", "--agents", "floor"]
        refused(capsys, [command, *args, "--out", out], f"holds a damaged pobax-{command}.json")
        assert [p.name for p in out.iterdir()] == [mark.name] and mark.read_text() == text


# --- 4. benchmark --merge checks every record before copying ---------------------------------------------------

def test_merge_of_a_malformed_record_copies_nothing(tmp_path, capsys):
    src = tmp_path / "src"
    (src / "agents" / "tmaze_5").mkdir(parents=True)
    (src / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    (src / "agents" / "tmaze_5" / "gru.json").write_text('{"nope": 1}')
    refused(capsys, ["benchmark", "--merge", src, "--out", tmp_path / "out"],
            "gru.json' is not a benchmark record pobax wrote (no env, agent")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("looped", ["--merge", "--out"])
def test_merge_with_a_symlink_loop_is_one_line(tmp_path, capsys, looped):
    """A looping link as --merge or --out raised RuntimeError ("Symlink loop") from Path.resolve, a traceback."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    src = tmp_path / "src"
    src.mkdir()
    (src / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    args = {"--merge": tmp_path / "a", "--out": tmp_path / "out"} if looped == "--merge" else \
        {"--merge": src, "--out": tmp_path / "a"}
    refused(capsys, ["benchmark", "--merge", args["--merge"], "--out", args["--out"]],
            f"{looped} {str(tmp_path / 'a')!r} is a symbolic link that leads back to itself")
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def smoke_bench(tmp_path_factory) -> Path:
    """A benchmark directory of T-Maze 5's floor at the smoke budget (copy it before changing it)."""
    out = tmp_path_factory.mktemp("bench") / "b"
    cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--quiet", "--out", str(out)])
    return out


def test_merge_into_an_out_with_a_damaged_record_copies_nothing(tmp_path, capsys, smoke_bench):
    """--out's own records are checked with the sources' before anything is copied (a source's record was copied,
    and benchmark.json rewritten, before --out's damaged one was refused)."""
    src = smoke_bench
    out = tmp_path / "out"
    (out / "agents" / "tmaze_5").mkdir(parents=True)
    (out / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    for text in ("garbage", '{"env": 5}'):
        (out / "agents" / "tmaze_5" / "gru.json").write_text(text)
        before = digest(out)
        refused(capsys, ["benchmark", "--merge", src, "--out", out], "gru.json'")
        assert digest(out) == before


def test_an_edited_record_is_refused_naming_it_before_anything_is_written(tmp_path, capsys, smoke_bench):
    """A record edited into another shape: a benchmark into its directory, of its environment or another, is refused
    in a line naming it (it used to end in a KeyError at the tables), and nothing is written."""
    out = copy(smoke_bench, tmp_path / "out")
    record = out / "agents" / "tmaze_5" / "floor.json"
    sealed = json.loads(record.read_text())
    original = {k: v for k, v in sealed.items() if k not in ("sha256", "seals")}  # as records from before the seal
    shape = f"{str(record)!r} is not a benchmark record pobax wrote"
    for edit, *what in ((lambda r: {"env": 5}, shape, "(no agent, observability"),
                        (lambda r: {**r, "config": None}, shape, "(config is None)"),
                        (lambda r: {**r, "disc": {**r["disc"], "mean": "high"}}, shape, "(disc is not a mean"),
                        (lambda r: {k: v for k, v in r.items() if k != "device"}, shape, "(device is None)"),  # KeyError
                        (lambda r: {**r, "disc": {**r["disc"], "per_seed": ["a"]}}, shape, "per_seed is not a list"),
                        (lambda r: {**r, "selection": {"config": {}}}, shape, "a selection in a registry record"),
                        (lambda r: {**r, "protocol": "bogus"}, shape, "protocol is 'bogus', not one of"),
                        (lambda r: {**r, "protocol": "paper"}, "is a record of the 'paper' protocol and its "
                                                                "directory's benchmark.json says 'registry'"),
                        (lambda r: {**r, "total_steps": 2 ** 70}, shape, "total_steps is 1180591620717411303424"),
                        (lambda r: {**r, "label": "floor\n| x |"}, shape, "label 'floor\\n| x |' holds a control"),
                        (lambda r: {**sealed, "disc": {**r["disc"], "mean": 99.0}}, "was edited after it was written"),
                        (lambda r: {**r, "seals": True, "disc": {**r["disc"], "mean": 99.0}}, "has no seal")):
        record.write_text(json.dumps(edit(original)))
        before = digest(out)
        for env in ("tmaze_5", "tmaze_6"):
            refused(capsys, ["benchmark", "--envs", env, "--agents", "floor", "--budget", "smoke", "--out", out],
                    f"{str(record)!r}", *what)
        refused(capsys, ["benchmark", "--merge", out, "--out", tmp_path / "m"], f"{str(record)!r}", *what)
        assert digest(out) == before and not (tmp_path / "m").exists()


def test_an_edited_protocol_in_benchmark_json_is_named_not_taken_for_the_directory(tmp_path, capsys, smoke_bench):
    """benchmark.json's protocol edited to 'paper' over registry records: a registry benchmark into it was told
    "--out holds the 'paper' protocol's results; pass another --out", as if the directory held paper records."""
    out = copy(smoke_bench, tmp_path / "out")
    meta = json.loads((out / "benchmark.json").read_text())
    (out / "benchmark.json").write_text(json.dumps({**meta, "protocol": "paper"}))
    before = digest(out)
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--out", out],
            "is a record of the 'registry' protocol and its directory's benchmark.json says 'paper'",
            "one of the two was edited")
    assert digest(out) == before


def test_merge_refuses_a_record_of_another_budget_for_one_environment(tmp_path, capsys, smoke_bench):
    """A record trained at other steps was merged beside the table's others (its row read 'smoke (768 × 2)')."""
    out = copy(smoke_bench, tmp_path / "out")
    src = tmp_path / "src"
    (src / "agents" / "tmaze_5").mkdir(parents=True)
    (src / "benchmark.json").write_text('{"envs": ["tmaze_5"], "calls": []}')
    record = json.loads((out / "agents" / "tmaze_5" / "floor.json").read_text())
    (src / "agents" / "tmaze_5" / "gru.json").write_text(json.dumps(seal_record({**record, "agent": "gru",
                                                                                "total_steps": 200000})))
    before = digest(out)
    refused(capsys, ["benchmark", "--merge", src, "--out", out], "gru.json' was trained at smoke (200,000 steps × 2",
            "one table holds one budget per environment")
    assert digest(out) == before


def test_merge_refuses_a_sweep_part_of_another_budget(tmp_path, capsys):
    """A finished protocol sweep part trained at other steps (a smoke run's) was copied into --out's sweep of the
    paper's budget; the next benchmark there refused it by name. Merge now refuses it first, naming both parts."""
    import shutil

    shipped = Path(__file__).resolve().parents[1] / "results" / "protocol"
    sweep = Path("runs") / "battleship_10" / "gru-sweep"
    first, second, third = sorted(p.name for p in (shipped / sweep).iterdir())[:3]
    for d, parts in (("out", (first,)), ("src", (second, third))):
        (tmp_path / d).mkdir()
        shutil.copy(shipped / "benchmark.json", tmp_path / d / "benchmark.json")
        for part in parts:
            shutil.copytree(shipped / sweep / part, tmp_path / d / sweep / part)
    config = json.loads((tmp_path / "src" / sweep / third / "config.json").read_text())
    config["config"]["total_steps"] = 100_000
    (tmp_path / "src" / sweep / third / "config.json").write_text(json.dumps(config))
    before = digest(tmp_path / "out")
    refused(capsys, ["benchmark", "--merge", tmp_path / "src", "--out", tmp_path / "out"],
            f"{str(tmp_path / 'src' / sweep / third)!r} was trained with total_steps 100000, "
            f"{str(tmp_path / 'out' / sweep / first)!r} with 10000000", "the parts of one sweep train at one budget")
    assert digest(tmp_path / "out") == before
    config["config"].update(total_steps=10_000_000, env_options=["map_seed=1"])  # a list, not a hyperparameter
    (tmp_path / "src" / sweep / third / "config.json").write_text(json.dumps(config))
    refused(capsys, ["benchmark", "--merge", tmp_path / "src", "--out", tmp_path / "out"],
            "was trained with env_options ['map_seed=1'],")
    shutil.rmtree(tmp_path / "src" / sweep / third)  # the part of the same budget is merged...
    config = json.loads((tmp_path / "src" / sweep / second / "config.json").read_text())
    config["config"].update(init="ppo", env_options=[])  # ...written by a later pobax: fields added since, defaults
    (tmp_path / "src" / sweep / second / "config.json").write_text(json.dumps(config))
    cli.main(["benchmark", "--merge", str(tmp_path / "src"), "--out", str(tmp_path / "out")])
    assert "merged 0 records and 1 finished sweep part (the protocol" in capsys.readouterr().out
    assert (tmp_path / "out" / sweep / second / "summary.json").read_bytes() == \
        (shipped / sweep / second / "summary.json").read_bytes()
    assert json.loads((tmp_path / "out" / sweep / second / "config.json").read_text()) == config


def test_a_benchmark_of_another_budget_beside_an_environments_records_is_refused(tmp_path, capsys, smoke_bench):
    """A second benchmark into one --out at other steps or seeds trained its agent beside the environment's records
    (the row labelled with the others' budget, the gap judged across them), which `--merge` refuses."""
    out = copy(smoke_bench, tmp_path / "out")
    before = digest(out)
    for extra in (["--total-steps", "1536"], ["--num-seeds", "3"]):
        refused(capsys, ["benchmark", "--envs", "tmaze_5", "--agents", "ceiling", "--budget", "smoke", *extra, "--out",
                         out], "floor.json' holds tmaze_5 at smoke (768 steps × 2 seeds)",
                "one table holds one budget per environment")
    assert digest(out) == before


@pytest.mark.slow
def test_agents_one_budget_gives_other_steps_or_seeds_share_a_table(tmp_path, capsys, smoke_bench):
    """At one budget agents may differ (the protocol evaluates λ-discrepancy on 32 smoke seeds, the floor on 8; the
    mazes' smoke ceiling trains 4× their floor's steps): adding one to a table, by a benchmark continued after an
    interruption or by --merge, was refused as another budget."""
    protocol = ["--envs", "tmaze_5", "--protocol", "paper", "--budget", "smoke", "--quiet"]
    cli.main(["benchmark", *protocol, "--agents", "floor", "--part-steps", "600", "--out", str(tmp_path / "p")])
    cli.main(["benchmark", *protocol, "--agents", "floor", "ld", "--dry-run", "--out", str(tmp_path / "p")])
    record = json.loads((tmp_path / "p" / "agents" / "tmaze_5" / "floor.json").read_text())
    (src := tmp_path / "src" / "agents" / "tmaze_5").mkdir(parents=True)
    (tmp_path / "src" / "benchmark.json").write_text((tmp_path / "p" / "benchmark.json").read_text())
    (src / "ld.json").write_text(json.dumps(seal_record({**record, "agent": "ld", "double_critic": True,
                                                         "num_seeds": 32})))
    cli.main(["benchmark", "--merge", str(tmp_path / "src"), "--out", str(tmp_path / "p")])
    assert (tmp_path / "p" / "agents" / "tmaze_5" / "ld.json").exists()
    (src / "ld.json").unlink()
    (src / "gru.json").write_text(json.dumps(seal_record({**record, "agent": "gru", "num_seeds": 9})))  # no plan
    capsys.readouterr()
    refused(capsys, ["benchmark", "--merge", tmp_path / "src", "--out", tmp_path / "p"],
            "gru.json' was trained at smoke (768 steps × 9 seeds", "one table holds one budget per environment")


def test_a_record_merged_while_a_benchmark_trains_that_agent_is_kept(tmp_path, capsys, smoke_bench):
    """A `--merge` of an agent's record while a benchmark into the same --out trained that agent: the merge said
    "added", then the benchmark wrote its own record over it. The first record written is kept, the other named."""
    out = tmp_path / "out"
    merged = []

    def merge_once(chunk):
        if not merged:
            merged.append(cli.main(["benchmark", "--merge", str(smoke_bench), "--out", str(out)]))

    cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--seed", "7", "--quiet",
              "--out", str(out)], on_chunk=merge_once)
    err = capsys.readouterr().err
    record = out / "agents" / "tmaze_5" / "floor.json"
    assert merged and f"{str(record)!r} was written by another process while this one trained it" in err, err
    assert record.read_text() == (smoke_bench / "agents" / "tmaze_5" / "floor.json").read_text()
    assert (out / "runs" / "tmaze_5" / "floor" / "summary.json").exists()  # this one's run, where it says


def test_a_record_of_another_budget_merged_while_a_benchmark_trains_keeps_one_table_one_budget(tmp_path, capsys,
                                                                                               smoke_bench):
    """A `--merge` of another agent's record at another budget while a benchmark into the same --out trained: the
    plan's budget check ran before training, so the benchmark's record was written beside it, two budgets in one
    table. The record found first is kept; this one's finished run is named, and once the other budget's records are
    moved out the same command reads that run instead of training it."""
    src, out = tmp_path / "src", tmp_path / "out"
    shutil.copytree(smoke_bench, src)
    floor = src / "agents" / "tmaze_5" / "floor.json"
    record = json.loads(floor.read_text())
    floor.unlink()
    (src / "agents" / "tmaze_5" / "gru.json").write_text(json.dumps(seal_record(
        {**record, "agent": "gru", "budget": "reduced"})))
    merged = []

    def merge_once(chunk):
        if not merged:
            merged.append(cli.main(["benchmark", "--merge", str(src), "--out", str(out)]))

    command = ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--seed", "7", "--quiet",
               "--out", str(out)]
    cli.main(command, on_chunk=merge_once)
    err = capsys.readouterr().err
    run = out / "runs" / "tmaze_5" / "floor"
    assert merged and "one table holds one budget per environment, so that record is kept" in err, err
    assert f"Its finished run is in {str(run)!r}" in err
    assert sorted(p.name for p in (out / "agents" / "tmaze_5").iterdir()) == ["gru.json"]
    assert [r.split(",")[1] for r in (out / "benchmark.csv").read_text().splitlines()[1:]] == ["gru"]
    sessions = (run / "sessions.json").read_bytes()
    (out / "agents" / "tmaze_5" / "gru.json").rename(tmp_path / "gru.json")
    cli.main(command)
    assert (out / "agents" / "tmaze_5" / "floor.json").exists()
    assert (run / "sessions.json").read_bytes() == sessions  # read, not trained again


@pytest.mark.slow
def test_a_benchmark_trains_the_agents_another_process_does_not_and_says_which(tmp_path, capsys):
    """Two benchmarks into one --out with an agent in common: the second stopped at it ("pass another --out"), its
    later agents never trained. It trains those, then names the one left to the other process (exit 1)."""
    out = tmp_path / "out"
    (run := out / "runs" / "tmaze_5" / "floor").mkdir(parents=True)
    (out / "benchmark.json").write_text('{"envs": [], "calls": []}')
    holder = RunDir(run)
    holder.hold()  # as another process training it
    try:
        with pytest.raises(SystemExit) as e:
            cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "ceiling", "--budget", "smoke",
                      "--quiet", "--out", str(out)])
    finally:
        holder.release()
    err = capsys.readouterr().err
    assert e.value.code == 1 and "1 of 2 agents (tmaze_5 / floor) were being trained by another process" in err, err
    assert (out / "agents" / "tmaze_5" / "ceiling.json").exists() and not (out / "agents" / "tmaze_5" / "floor.json").exists()


def test_results_lists_a_run_whose_config_json_is_damaged(tmp_path, finished, capsys):
    root = tmp_path / "runs"
    root.mkdir()
    run = copy(finished, root / "a")
    (run / "config.json").write_text("{bad")  # was left out of the list silently
    cli.main(["results", "--root", str(root)])
    out, err = capsys.readouterr()
    assert " damaged " in out and "config.json' is not a run configuration pobax wrote" in err, (out, err)


@pytest.mark.parametrize("text, what", [("[]", "(a JSON list, not an object)"), ("{}", "(envs is not a list"),
                                        ('{"envs": [], "calls": 3}', "(calls is not a list of calls)"),
                                        ('{"envs": [], "calls": [], "protocol": 7}', "(protocol is 7, not one of registry, paper)")])
def test_an_edited_benchmark_json_is_refused_naming_it(tmp_path, capsys, text, what):
    out = tmp_path / "out"
    out.mkdir()
    (out / "benchmark.json").write_text(text)
    message = f"{str(out / 'benchmark.json')!r} is not a benchmark.json pobax wrote"
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--dry-run", "--out", out], message, what)
    refused(capsys, ["benchmark", "--merge", out, "--out", tmp_path / "m"], message, what)
    assert (out / "benchmark.json").read_text() == text and not (tmp_path / "m").exists()


@pytest.mark.slow
def test_an_edited_sweep_part_summary_is_refused_naming_it(tmp_path, capsys):
    """A finished sweep part whose summary.json was edited into another shape (valid JSON): the protocol's
    selection and `--merge` refuse it in a line naming the file, and nothing is written."""
    bench = ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--protocol", "paper", "--budget", "smoke",
             "--part-steps", "600", "--quiet", "--out", tmp_path / "p"]
    cli.main([str(a) for a in bench])
    capsys.readouterr()
    first = json.loads((tmp_path / "p" / "agents" / "tmaze_5" / "floor.json").read_text())
    (tmp_path / "p" / "agents" / "tmaze_5" / "floor.json").unlink()  # the record again, from the parts
    part = sorted((tmp_path / "p" / "runs" / "tmaze_5" / "floor-sweep").iterdir())[0]
    summary = json.loads((part / "summary.json").read_text())
    unsealed = pre_seal(summary)  # as summaries from before the seal read
    sessions = json.loads((part / "sessions.json").read_text())
    (part / "sessions.json").write_text(json.dumps([{k: v for k, v in x.items() if k != "seals"} for x in sessions]))
    ci = {"mean": 1.0}
    for edit, what in ((lambda s: {"sets": []}, "(no sets)"),
                       (lambda s: {**s, "sets": [{**s["sets"][0], "lambda0": "high"}]}, "set 0 has a hyperparameter"),
                       (lambda s: {**s, "sets": [{**s["sets"][0], "disc_return_auc": ci}]}, "without its mean and conf"),
                       (lambda s: {**s, "sets": [{k: v for k, v in s["sets"][0].items() if k != "hp_index"}]},
                        "set 0 has no hp_index"),  # was a KeyError in a sweep's selection
                       (lambda s: {**s, "best_by_auc": -1}, "best_by_auc -1 is not one of its sets"),
                       (lambda s: {**s, "steps_per_s": "fast"}, "steps_per_s is 'fast'"),  # a record nothing read
                       (lambda s: {**s, "wall_s": "x"}, "wall_s is 'x'"),
                       (lambda s: {**s, "sessions": [5]}, "its sessions are not a list of objects"),
                       (lambda s: {**summary, "wall_s": 1.0}, "was edited after its run finished"),  # sealed
                       (lambda s: {**{k: v for k, v in summary.items() if k != "sha256"},
                                   "sets": [{**summary["sets"][0], "disc_return_auc": {
                                       **summary["sets"][0]["disc_return_auc"], "mean": 99.0}}]},
                        "has no seal")):  # its seal removed to pass an edited AUC: was selected by it, exit 0
        (part / "summary.json").write_text(json.dumps(edit(unsealed)))
        before = digest(tmp_path / "p" / "runs"), digest(tmp_path / "p" / "agents")
        refused(capsys, bench, f"{str(part / 'summary.json')!r}", what)
        refused(capsys, [*(a for a in bench if a != "--quiet"), "--dry-run"], what)  # the plan reads it (TypeError)
        refused(capsys, ["benchmark", "--merge", tmp_path / "p", "--out", tmp_path / "m"], what)
        assert (digest(tmp_path / "p" / "runs"), digest(tmp_path / "p" / "agents")) == before  # runs and records
        assert not (tmp_path / "m").exists()
    (part / "summary.json").write_text(json.dumps(summary))
    (part / "config.json").write_text("{bad")  # was copied by --merge as text, then refused by the next benchmark
    refused(capsys, ["benchmark", "--merge", tmp_path / "p", "--out", tmp_path / "m"], "config.json'")
    assert not (tmp_path / "m").exists()
    for text in ("{}", "[1]"):  # read to continue the split at another --part-steps: was a KeyError or TypeError
        (part / "config.json").write_text(text)
        refused(capsys, [a for a in bench if a not in ("--part-steps", "600")], f"{str(part / 'config.json')!r}")
    (part / "config.json").unlink()  # was "[Errno 2] No such file or directory"
    refused(capsys, bench, f"{str(part / 'config.json')!r} is missing from a finished sweep part")
    for args in ([a for a in bench if a not in ("--part-steps", "600")],  # read to continue the split: was "[Errno 2]"
                 ["benchmark", "--merge", tmp_path / "p", "--out", tmp_path / "m"]):
        refused(capsys, args, f"{str(part / 'config.json')!r} is missing from a finished sweep part")
    assert not (tmp_path / "m").exists()
    # a finished record is reused only for the same evaluation seeds (--num-seeds 3 reused this 2-seed one)
    (record := tmp_path / "q" / "agents" / "tmaze_5" / "floor.json").parent.mkdir(parents=True)
    record.write_text(json.dumps(first))
    (tmp_path / "q" / "benchmark.json").write_text((tmp_path / "p" / "benchmark.json").read_text())
    refused(capsys, [*bench[:-1], tmp_path / "q", "--num-seeds", "3"],
            "differs in: the evaluation's seeds (--num-seeds)")


# --- 5. a killed benchmark takes its jobs with it ---------------------------------------------------------------

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


def test_ctrl_c_of_side_by_side_jobs_says_how_to_continue(capsys):
    """`benchmark --jobs 2` ends a Ctrl-C in a plain KeyboardInterrupt (no run directory of its own): it said only
    "interrupted", not that the same command continues."""
    from pobax._cli.commands import Benchmark

    with pytest.raises(SystemExit) as e:
        cli._interrupted(Benchmark(), KeyboardInterrupt())
    assert e.value.code == 130
    assert "the same command with the same --out continues" in capsys.readouterr().err


def test_a_benchmark_json_that_is_a_directory_and_a_bare_merge_are_one_line(tmp_path, capsys):
    """`benchmark.json` made a directory was "[Errno 21] Is a directory"; `--merge` with no directory after it asked
    for --suite or --envs."""
    (tmp_path / "b" / "benchmark.json").mkdir(parents=True)
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--out",
                     tmp_path / "b"], f"{str(tmp_path / 'b' / 'benchmark.json')!r} is a directory")
    refused(capsys, ["benchmark", "--merge", "--out", tmp_path / "m"], "--merge needs the benchmark output directories")
    assert not (tmp_path / "m").exists() and [p.name for p in (tmp_path / "b").iterdir()] == ["benchmark.json"]


def test_a_run_another_process_finishes_while_this_one_waits_to_resume_it_is_reused(tmp_path, stopped, monkeypatch):
    """Two benchmarks into one --out: the second found an agent's run interrupted (no summary.json) while the first
    was finishing it, then found it finished when it took the directory to resume it, and stopped with "already
    finished: nothing to resume" (exit 2, its remaining agents untrained). The finished run is reused instead."""
    from pobax.eval import _run

    run = copy(stopped, tmp_path / "r")
    real = _run.train

    def other_process_finishes_it_first(cfg, path, **kw):
        if kw.get("resume") and not (Path(path) / "summary.json").exists():
            real(cfg, path, progress=False, resume=True)  # the other process, between the check and the hold
        return real(cfg, path, **kw)

    monkeypatch.setattr(_run, "train", other_process_finishes_it_first)
    metrics, summary, where = _run.train_or_reuse(CFG, run, progress=False)
    assert where == run and summary == RunDir(run).read_summary() and len(metrics) > 0


def test_a_directory_another_process_is_creating_is_not_moved_aside(tmp_path):
    """A run directory without config.json is kept aside as `.incomplete-…` before training again; one that another
    process holds (creating it: config.json comes next) was moved from under it. It is refused as busy."""
    from pobax.eval._results import RunDirBusyError
    from pobax.eval._run import train_or_reuse

    run = tmp_path / "r"
    (run / "metrics").mkdir(parents=True)
    other = RunDir(run)
    other.hold()
    try:
        with pytest.raises(RunDirBusyError, match="being trained by another process"):
            train_or_reuse(CFG, run, progress=False)
    finally:
        other.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"] and (run / "metrics").is_dir()


def test_an_agent_another_process_finishes_meanwhile_is_in_the_table_and_no_error(tmp_path, capsys, smoke_bench):
    """Two benchmarks into one --out: the one that skipped an agent the other was training said "run the same command
    again" (exit 1) even when the other had finished it before this one ended; its record is now in the table."""
    import shutil

    out = tmp_path / "out"
    (run := out / "runs" / "tmaze_5" / "floor").mkdir(parents=True)
    (out / "benchmark.json").write_text('{"envs": [], "calls": []}')
    holder = RunDir(run)
    holder.hold()  # as another process training it
    finished = []

    def other_process_finishes(chunk):  # while this one trains the ceiling
        if not finished:
            finished.append(chunk)
            holder.release()
            shutil.rmtree(run)
            shutil.copytree(smoke_bench / "runs" / "tmaze_5" / "floor", run)
            (out / "agents" / "tmaze_5").mkdir(parents=True, exist_ok=True)
            shutil.copy(smoke_bench / "agents" / "tmaze_5" / "floor.json", out / "agents" / "tmaze_5")

    try:
        cli.main(["benchmark", "--envs", "tmaze_5", "--agents", "floor", "ceiling", "--budget", "smoke", "--quiet",
                  "--out", str(out)], on_chunk=other_process_finishes)
    finally:
        holder.release()
    err = capsys.readouterr().err
    assert "skipped: The run in" in err and "were being trained by another process" not in err, err
    rows = (out / "benchmark.csv").read_text().splitlines()
    assert sorted(r.split(",")[1] for r in rows[1:]) == ["ceiling", "floor"], rows


def test_merge_refuses_a_sweep_part_trained_on_another_device_kind(tmp_path, capsys):
    """A Battleship λ-discrepancy part trained on an H100 when no H200 came was merged beside parts trained on H200s:
    the agent's record would read "NVIDIA H200 + NVIDIA H100 80GB HBM3" and stay out of the protocol's table once
    its evaluation finished. Merge now refuses the part, naming both devices; the same provenance merges."""
    import shutil

    shipped = Path(__file__).resolve().parents[1] / "results" / "protocol"
    sweep = Path("runs") / "battleship_10" / "gru-sweep"
    first, second = sorted(p.name for p in (shipped / sweep).iterdir())[:2]
    for d, part in (("out", first), ("src", second)):
        (tmp_path / d).mkdir()
        shutil.copy(shipped / "benchmark.json", tmp_path / d / "benchmark.json")
        shutil.copytree(shipped / sweep / part, tmp_path / d / sweep / part)
    sessions_file = tmp_path / "src" / sweep / second / "sessions.json"
    sessions = json.loads(sessions_file.read_text())
    assert {s["device"] for s in sessions} == {"NVIDIA H200"}
    sessions_file.write_text(json.dumps([dict(s, device="NVIDIA H100 80GB HBM3") for s in sessions]))
    before = digest(tmp_path / "out")
    refused(capsys, ["benchmark", "--merge", tmp_path / "src", "--out", tmp_path / "out"],
            f"{str(tmp_path / 'src' / sweep / second)!r} was trained on NVIDIA H100 80GB HBM3 (c33ea9b71539-archive",
            f"{str(tmp_path / 'out' / sweep / first)!r} on NVIDIA H200 (c33ea9b71539-archive",
            "stays out of the protocol's table")
    assert digest(tmp_path / "out") == before
    sessions_file.write_text('{"device": "NVIDIA H200"}')  # not a list of sessions: refused by name
    refused(capsys, ["benchmark", "--merge", tmp_path / "src", "--out", tmp_path / "out"],
            f"{str(tmp_path / 'src' / sweep / second)!r}: its sessions.json is not one pobax wrote")
    sessions_file.write_text(json.dumps(sessions))  # trained where the others trained: merged
    cli.main(["benchmark", "--merge", str(tmp_path / "src"), "--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / sweep / second / "summary.json").is_file()


def test_a_benchmarks_figure_is_never_written_through_a_link_or_over_a_users_file(tmp_path, capsys, smoke_bench):
    """benchmark.png as a link to a file outside --out: the text file was replaced by the figure, as was a text file
    named benchmark.png; a link to an image was written through to it."""
    bench = ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--quiet"]
    out = copy(smoke_bench, tmp_path / "out")
    figure = out / "benchmark.png"
    thesis = tmp_path / "thesis.txt"
    thesis.write_text("chapter 1")
    figure.unlink()
    figure.symlink_to(thesis)
    refused(capsys, [*bench, "--out", out], "the figure", "benchmark.png' exists and is not a PNG image")
    refused(capsys, ["benchmark", "--merge", smoke_bench, "--out", out], "benchmark.png' exists and is not a PNG")
    assert thesis.read_text() == "chapter 1"
    image = tmp_path / "mine.png"
    image.write_bytes((smoke_bench / "benchmark.png").read_bytes())
    figure.unlink()
    figure.symlink_to(image)
    kept = image.read_bytes()
    cli.main([*bench, "--out", str(out)])
    assert image.read_bytes() == kept and not figure.is_symlink() and figure.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("damage", ["file", "loop"])
def test_merge_refuses_a_source_whose_records_folder_is_not_a_directory(tmp_path, capsys, smoke_bench, damage):
    """A source's agents/ (or agents/ENV/) as a file or a looping link: it merged 0 records, exit 0."""
    for folder in ("agents", "agents/tmaze_5"):
        src = copy(smoke_bench, tmp_path / f"src-{folder.replace('/', '-')}")
        shutil.rmtree(src / folder)
        if damage == "file":
            (src / folder).write_text("x")
        else:
            (src / folder).symlink_to(src / folder)
        refused(capsys, ["benchmark", "--merge", src, "--out", tmp_path / "new"], f"{str(src / folder)!r} is not a "
                "directory")
        assert not (tmp_path / "new").exists()


def test_a_directory_where_a_file_is_written_says_what_to_do(tmp_path, capsys, smoke_bench):
    """benchmark.md as a directory: the bare "[Errno 21] Is a directory" now says what stands there and what to do."""
    out = copy(smoke_bench, tmp_path / "out")
    (out / "benchmark.md").unlink()
    (out / "benchmark.md").mkdir()
    refused(capsys, ["benchmark", "--envs", "tmaze_5", "--agents", "floor", "--budget", "smoke", "--quiet", "--out",
                     out], "benchmark.md", "a directory stands where pobax writes a file: move it aside")
