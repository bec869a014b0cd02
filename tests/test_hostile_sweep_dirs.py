"""`sweep` and `gap` output directories used as a hostile but fair user would: two calls claiming one new --out at
once, a sweep continued with other flags after one of its programs was removed, and a gap report's --out edited
between calls. Tiny T-Maze 5 runs on the CPU (`_hostile.py`)."""

import json
import shutil

import pytest

import cli
from pobax.eval import _files

from _hostile import TINY, copy, digest, refused

SWEEP = ["sweep", *TINY, "--lr", "1e-3", "2e-3", "--axis", "hidden_size=8,16"]
GAP = ["gap", "--env", "tmaze_5", "--hidden-size", "8", "--total-steps", "4096", "--num-seeds", "2", "--fast-compile",
       "--quiet"]


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """A finished sweep of two programs (copy it before changing it)."""
    out = tmp_path_factory.mktemp("sweep") / "s"
    cli.main([str(a) for a in [*SWEEP, "--out", out]])
    return out


@pytest.fixture(scope="module")
def gapped(tmp_path_factory):
    """A finished gap report of the floor and the GRU (copy it before changing it)."""
    out = tmp_path_factory.mktemp("gap") / "g"
    cli.main([str(a) for a in [*GAP, "--agents", "floor", "gru", "--out", out]])
    return out


@pytest.mark.parametrize("command", ["sweep", "gap"])
def test_two_calls_claiming_one_new_out_at_once_the_second_is_refused(tmp_path, capsys, monkeypatch, command):
    """Two sweeps of other axes (or gaps of other environments) started at once into one new --out both found it
    empty, then each wrote its marker only where none stood yet: both trained (3 of 6 tries with two processes),
    and the out held one call's pobax-sweep.json with the other's best.json and sweep.json (written over)."""
    out = tmp_path / "o"
    other = ({"command": "sweep", "env": "tmaze_5", "memory": "gru", "axes": {"hidden_size": [32]}, "grid": {}}
             if command == "sweep" else {"command": "gap", "env": "tmaze_6"})
    check, claimed = _files.writable_dir, []

    def another_process_claims_it_meanwhile(path):  # between this call's look at --out and its marker
        if not claimed:
            claimed.append(True)
            _files.claim_out(out, _files.OUT_MARKERS[command], other)
        check(path)

    monkeypatch.setattr(_files, "writable_dir", another_process_claims_it_meanwhile)
    args = [*SWEEP] if command == "sweep" else [*GAP, "--agents", "floor"]
    refused(capsys, [*args, "--out", out], "holds another call's results")
    assert claimed and sorted(p.name for p in out.iterdir()) == [f"pobax-{command}.json"]  # nothing trained
    assert json.loads((out / f"pobax-{command}.json").read_text()) == other  # the other call's, kept


def test_a_sweep_continued_with_other_flags_is_refused_before_training(tmp_path, capsys, swept):
    """With one program of a finished sweep removed, the same sweep with another --total-steps trained that program
    again at the new budget, then refused the next one: the --out held programs of two budgets, and neither
    command continued it any more."""
    out = copy(swept, tmp_path / "s")
    shutil.rmtree(out / "hidden_size=8")
    before = digest(out)
    refused(capsys, [*SWEEP, "--total-steps", "8192", "--out", out],
            f"{str(out / 'hidden_size=16')!r} holds a run with another configuration (differs in: total_steps)")
    assert digest(out) == before and not (out / "hidden_size=8").exists()
    cli.main([str(a) for a in [*SWEEP, "--out", out]])  # the sweep as it began still continues
    assert (out / "hidden_size=8" / "summary.json").exists()


def _gap_json(out) -> dict:
    return json.loads((out / "gap.json").read_text())


def test_a_gap_report_keeps_only_what_an_earlier_agents_run_says(tmp_path, capsys, gapped):
    """The agents of an earlier call that a gap call does not train were reported with the fields of gap.json's
    entry as they stood: an edited lr or label was reported as the run's, an entry without its label was a KeyError
    and a label of another type a TypeError (tracebacks), and a run directory of another agent under the name (the
    floor's run as `gru`) was reported as that agent's returns."""
    out = copy(gapped, tmp_path / "g")
    report = _gap_json(out)
    gru = next(a for a in report["agents"] if a["name"] == "gru")
    for edit in ({"lr": 0.5, "agent": "lstm (partial)", "num_seeds": 30}, {"agent": None}, {"agent": 5}):
        entry = {k: v for k, v in gru.items() if k != "agent"} | {k: v for k, v in edit.items() if v is not None}
        (out / "gap.json").write_text(json.dumps({**report, "agents": [
            a if a["name"] != "gru" else entry for a in report["agents"]]}))
        cli.main([str(a) for a in [*GAP, "--agents", "floor", "--out", out]])
        capsys.readouterr()
        kept = next(a for a in _gap_json(out)["agents"] if a["name"] == "gru")
        assert {k: kept[k] for k in ("agent", "lr", "num_seeds")} == {k: gru[k] for k in ("agent", "lr", "num_seeds")}
        assert kept["disc_return"] == gru["disc_return"]
    (out / "gap.json").write_text(json.dumps(report))
    shutil.move(out / "gru", tmp_path / "gru")
    shutil.copytree(out / "floor", out / "gru")  # another agent's run under the GRU's name
    cli.main([str(a) for a in [*GAP, "--agents", "floor", "--out", out]])
    capsys.readouterr()
    assert [a["name"] for a in _gap_json(out)["agents"]] == ["floor"]  # not the floor's returns as the GRU's


@pytest.mark.parametrize("args, flag", [(["sweep", *TINY, "--axis", "hidden_size=8", "--axis", "num_envs=4"], "--axis"),
                                        (["train", *TINY, "--lr=1e-3", "--lr", "2e-3"], "--lr"),
                                        (["benchmark", "--envs", "tmaze_5", "--envs", "tmaze_6", "--dry-run"], "--envs")])
def test_a_flag_of_several_values_given_twice_is_refused_not_replaced(tmp_path, capsys, args, flag):
    """`--axis hidden_size=8 --axis num_envs=4` swept num_envs alone: the second flag replaced the first's values."""
    out = tmp_path / "o"
    refused(capsys, [*args, "--out", out], f"{flag} is given 2 times: give it once, with all its values")
    assert not out.exists()


def test_a_sweep_continued_with_its_axes_in_another_order_reuses_its_programs(tmp_path, capsys):
    """`--axis hidden_size=8 num_envs=4`, then `--axis num_envs=4 hidden_size=8` into the same --out was accepted as
    the same sweep and trained every program again under other names, beside the first ones."""
    out = tmp_path / "s"
    base = ["sweep", *TINY, "--out", out]
    cli.main([str(a) for a in [*base, "--axis", "hidden_size=8", "num_envs=4"]])
    before = digest(out)
    cli.main([str(a) for a in [*base, "--axis", "num_envs=4", "hidden_size=8"]])
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["hidden_size=8-num_envs=4"]
    assert {k: v for k, v in digest(out).items() if k.startswith("hidden_size=8-num_envs=4/")} == \
        {k: v for k, v in before.items() if k.startswith("hidden_size=8-num_envs=4/")}  # reused, not trained again


@pytest.mark.parametrize("damage", ["truncated best.json", "sweep.json a directory"])
def test_a_sweep_whose_results_cannot_be_written_is_refused_before_training(tmp_path, capsys, swept, damage):
    """A damaged best.json (not a preset) or a sweep.json replaced by a directory was refused only at the end, after
    every program had trained or been reused."""
    out = copy(swept, tmp_path / "s")
    shutil.rmtree(out / "hidden_size=8")
    if damage == "truncated best.json":
        (out / "best.json").write_text('{"pres')
        message = f"{str(out / 'best.json')!r} exists and is not a preset file pobax wrote"
    else:
        (out / "sweep.json").unlink()
        (out / "sweep.json").mkdir()
        message = f"{str(out / 'sweep.json')!r} exists and is not a file"
    before = digest(out)
    refused(capsys, [*SWEEP, "--out", out], message)
    assert digest(out) == before and not (out / "hidden_size=8").exists()  # nothing trained


def test_a_damaged_gap_json_does_not_drop_the_earlier_agents(tmp_path, capsys, gapped):
    """A truncated gap.json made the next report of a subset of agents leave the earlier ones out (exit 0), though
    their finished runs stood in --out."""
    out = copy(gapped, tmp_path / "g")
    gru = next(a for a in _gap_json(out)["agents"] if a["name"] == "gru")
    (out / "gap.json").write_text('{"env": "tmaze_5", "agen')
    cli.main([str(a) for a in [*GAP, "--agents", "floor", "--out", out]])
    capsys.readouterr()
    kept = {a["name"]: a for a in _gap_json(out)["agents"]}
    assert sorted(kept) == ["floor", "gru"] and kept["gru"]["disc_return"] == gru["disc_return"]
