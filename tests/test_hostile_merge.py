"""`pobax benchmark --merge` used against its grain: killed while it copies, racing another process writing into the
same --out, an --out inside the directory it merges from, a path with a newline. The shipped T-Maze 10 records
stand in for records trained elsewhere (nothing trains here)."""

import contextlib
import re
import json
from pathlib import Path

import pytest

import cli
from pobax.eval import _merge, merge_results
from pobax.eval._plan import BenchmarkError, benchmark_dir

from _hostile import ROOT, digest, refused

SHIPPED = ROOT / "results" / "agents" / "tmaze_10"


def _source(path: Path, agents: tuple[str, ...], **edit) -> Path:
    """A benchmark directory holding the shipped T-Maze 10 records of `agents` (each with the fields `edit`)."""
    (path / "agents" / "tmaze_10").mkdir(parents=True)
    (path / "benchmark.json").write_text(json.dumps({"envs": ["tmaze_10"], "calls": [{"command": f"from {path}"}]}))
    for name in agents:
        record = {**json.loads((SHIPPED / f"{name}.json").read_text()), **edit}
        (path / "agents" / "tmaze_10" / f"{name}.json").write_text(json.dumps(record))
    return path


class Killed(BaseException):
    """The merge's process ended here (as by SIGKILL: nothing of the merge runs after it)."""


def test_a_merge_killed_while_copying_leaves_an_out_that_the_same_merge_completes(tmp_path, monkeypatch):
    """Killed after its first record into a new --out, a merge left agents/ and no benchmark.json: the same merge
    again (and any benchmark into that --out, or another starting meanwhile) was refused, "holds other files and no
    benchmark.json". benchmark.json is now written before anything is copied."""
    src, out = _source(tmp_path / "src", ("floor", "gru", "ceiling")), tmp_path / "out"
    real, copied, accepted = _merge.atomic_write_text, [], []

    def killed_at_the_second_copy(path, text):
        if copied:
            accepted.append(benchmark_dir(out))  # another merge or benchmark starting into --out meanwhile
            raise Killed
        copied.append(path)
        real(path, text)

    monkeypatch.setattr(_merge, "atomic_write_text", killed_at_the_second_copy)
    with pytest.raises(Killed):
        merge_results(out, (src,))
    assert accepted == [out] and len(list((out / "agents").glob("*/*.json"))) == 1
    assert json.loads((out / "benchmark.json").read_text())["calls"] == []  # no call claims what is not there
    monkeypatch.setattr(_merge, "atomic_write_text", real)
    result = merge_results(out, (src,))  # the same merge again: completes it
    assert sorted(result["added"]) == sorted(f"tmaze_10/{n}" for n in ("floor", "gru", "ceiling")
                                             if n != copied[0].stem) and not result["kept"]
    for name in ("floor", "gru", "ceiling"):
        assert (out / "agents" / "tmaze_10" / f"{name}.json").read_bytes() == \
            (src / "agents" / "tmaze_10" / f"{name}.json").read_bytes()
    assert json.loads((out / "benchmark.json").read_text())["calls"][-1]["identical"] == [f"tmaze_10/{copied[0].stem}"]
    rows = (out / "benchmark.csv").read_text().splitlines()[1:]
    assert sorted(r.split(",")[1] for r in rows) == ["ceiling", "floor", "gru"]
    assert json.loads((out / "benchmark.json").read_text())["envs"] == ["tmaze_10"]
    assert not [p for p in out.rglob("*.tmp")]


def test_two_merges_of_other_budgets_into_one_out_at_once_keep_one_budget(tmp_path, monkeypatch):
    """Two merges into one --out at once, of records of one environment at other budgets: each checked --out before
    the other copied, so both were copied into one table (what either alone refuses). A merge now checks again under
    --out's lock, with what another process wrote meanwhile, and the later one is refused; nothing of it is copied."""
    out = tmp_path / "out"
    first = _source(tmp_path / "first", ("floor",))
    other = _source(tmp_path / "other", ("gru",), total_steps=200_000)
    real, raced = _merge.shared_files, []

    @contextlib.contextmanager
    def the_other_merge_first(path):  # the other process takes --out's lock between this one's check and its own
        if not raced:
            raced.append(None)  # (once: the other merge takes the lock itself)
            raced[0] = merge_results(out, (other,))
        with real(path):
            yield

    monkeypatch.setattr(_merge, "shared_files", the_other_merge_first)
    with pytest.raises(BenchmarkError, match="one table holds one budget per environment"):
        merge_results(out, (first,))
    assert raced[0]["added"] == ["tmaze_10/gru"]
    assert sorted(p.name for p in (out / "agents" / "tmaze_10").iterdir()) == ["gru.json"]
    assert [r.split(",")[1] for r in (out / "benchmark.csv").read_text().splitlines()[1:]] == ["gru"]


def test_an_out_inside_the_directory_merged_from_is_refused(tmp_path, capsys):
    """--out in a source's agents/ (a new folder there): the merge wrote its benchmark.json where the source keeps its
    records' folders, and every later read of the source refused it as a damaged record. An --out inside a source
    is refused, the source untouched."""
    src = _source(tmp_path / "src", ("floor",))
    before = digest(src)
    (tmp_path / "link").symlink_to(src / "agents")
    for out in (src / "agents" / "new", src / "merged", tmp_path / "link" / "new"):
        refused(capsys, ["benchmark", "--merge", src, "--out", out], f"--out {str(out)!r} is inside --merge "
                f"{str(src)!r}", "pass an --out outside it")
        assert digest(src) == before and not (src / "agents" / "new").exists()
    cli.main(["benchmark", "--merge", str(src), "--out", str(tmp_path / "out")])  # still read as it was
    assert "merged 1 record into" in capsys.readouterr().out


def test_a_newline_in_out_is_escaped_in_the_merge_summary(tmp_path, capsys):
    """"merged N records into OUT" printed OUT's newline as it is, breaking the line (its "results:" line escaped it)."""
    src, out = _source(tmp_path / "src", ("floor",)), tmp_path / "out\nx"
    cli.main(["benchmark", "--merge", str(src), "--out", str(out)])
    lines = capsys.readouterr().out.splitlines()
    assert f"merged 1 record into {str(out).replace(chr(10), chr(92) + 'n')}: tmaze_10/floor" in lines, lines[-3:]


def test_a_source_record_edited_after_the_merges_checks_is_refused_not_copied(tmp_path, monkeypatch, capsys):
    """A source record another process edited between the merge's last check (under --out's lock) and its copy was
    copied as it then was, unchecked. Each record is checked as it is copied: the edited one is refused by name and
    not copied; restored, the same merge completes."""
    src, out = _source(tmp_path / "src", ("floor", "gru")), tmp_path / "out"
    record = src / "agents" / "tmaze_10" / "floor.json"
    good = record.read_text()
    real, calls = _merge._check, []

    def edited_after_the_check(*args):  # (called before --out's lock is taken, then under it: the last check)
        protocol = real(*args)
        calls.append(None)
        if len(calls) == 2:
            record.write_text(json.dumps({**json.loads(good), "disc": {"mean": 99.0}}))  # no interval: not a record
        return protocol

    monkeypatch.setattr(_merge, "_check", edited_after_the_check)
    refused(capsys, ["benchmark", "--merge", src, "--out", out], str(record))
    assert not (out / "agents" / "tmaze_10" / "floor.json").exists()
    monkeypatch.setattr(_merge, "_check", real)
    record.write_text(good)
    assert sorted(merge_results(out, (src,))["added"]) == ["tmaze_10/floor", "tmaze_10/gru"]


@pytest.mark.parametrize("block", [{"mean": 1.0}, {"mean": 1.0, "ci_low": 0.5}, {"mean": 1.0, "ci_low": None}])
def test_a_record_whose_interval_is_missing_is_refused_by_name(tmp_path, block):
    """A record's statistic without its interval's keys passed the check (a missing key read as None, a statistic
    that has none) and then failed the tables with a KeyError; a key missing is refused, a null kept."""
    from pobax.eval._records import RecordError, check_record  # noqa: PLC0415

    record = json.loads((SHIPPED / "floor.json").read_text())
    path = tmp_path / "agents" / "tmaze_10" / "floor.json"
    check_record(record, path)
    with pytest.raises(RecordError, match="disc is not a mean with its confidence interval"):
        check_record({**record, "disc": block}, path)
    check_record({**record, "disc": {"mean": None, "ci_low": None, "ci_high": None}}, path)  # every seed diverged


@pytest.mark.parametrize("edit, message", [
    (lambda r: r.pop("paper_value"), "no paper_value"),
    (lambda r: r.pop("env_steps_per_s"), "no env_steps_per_s"),
    (lambda r: r.update(reference=[1]), "reference is [1], not an object"),
    (lambda r: r.update(episode_metrics=[1]), "episode_metrics are not per-episode quantities"),
    (lambda r: r.update(episode_metrics={"wake_up": 0.5}), "episode_metrics are not per-episode quantities"),
])
def test_a_record_missing_what_the_tables_read_is_refused_by_name(tmp_path, edit, message):
    """Keys the tables and report read (`_report`) that the check read with .get: a record without them passed and
    then failed the tables with a KeyError or TypeError. Each is refused by name; `pobax benchmark` writes them all."""
    from pobax.eval._records import RecordError, check_record  # noqa: PLC0415

    record = json.loads((SHIPPED / "floor.json").read_text())
    edit(record)
    with pytest.raises(RecordError, match=re.escape(message)):
        check_record(record, tmp_path / "agents" / "tmaze_10" / "floor.json")
