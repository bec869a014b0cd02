"""`benchmarks/probe_record.py`: a one-factor probe's arms side by side, with the configuration fields that differ."""

import dataclasses
import importlib.util
import json
import re
import shutil
from pathlib import Path

import pytest

from pobax.agent import TrainConfig
from pobax.eval import run_benchmark, train
from pobax.eval._records import seal_record

_spec = importlib.util.spec_from_file_location(
    "probe_record", Path(__file__).resolve().parents[1] / "benchmarks" / "probe_record.py")
probe_record = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(probe_record)


def _edited_copy(src: Path, dst: Path, edit) -> Path:
    """A copy of a benchmark output whose floor record `edit` changed (what another arm would have trained)."""
    shutil.copytree(src, dst)
    f = dst / "agents" / "tmaze_5" / "floor.json"
    record = json.loads(f.read_text())
    edit(record)
    f.unlink()
    (f.parent / f"{record['agent']}.json").write_text(json.dumps(seal_record(record)))  # as pobax writes one
    return dst


def _two_agents(tmp_path: Path) -> Path:
    """An arm holding two agent records (the floor's, and a copy named gru)."""
    d = tmp_path / "two"
    shutil.copytree(tmp_path / "a", d)
    f = d / "agents" / "tmaze_5" / "floor.json"
    record = json.loads(f.read_text())
    record.update(agent="gru")
    (f.parent / "gru.json").write_text(json.dumps(seal_record(record)))
    return d


@pytest.mark.slow  # 12 s on 2 cores: two smoke benchmarks
def test_a_probes_arms_are_recorded_with_the_fields_that_differ(tmp_path, capsys):
    for name, more in (("a", {}), ("b", {"lr": (1e-3,)})):  # two arms trained, differing in the step size
        run_benchmark(("tmaze_5",), budget="smoke", out=tmp_path / name, agents=("floor",), progress=False,
                      overrides={"num_chunks": 2, **more})
    out = tmp_path / "probe.json"
    assert probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", f"b={tmp_path / 'b'}", "--what", "lr",
                              "--command", "pobax benchmark ...", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["factors"] == {"tmaze_5/floor": ["lr"]} and set(record["arms"]) == {"a/floor", "b/floor"}
    a = json.loads((tmp_path / "a" / "agents" / "tmaze_5" / "floor.json").read_text())
    arm = record["arms"]["a/floor"]
    assert arm["disc"]["per_seed"] == a["disc"]["per_seed"] and arm["pobax_commit"] == a["pobax_commit"]
    assert len(arm["disc_by_tenth_of_training"]) == 10
    assert arm["disc_by_tenth_of_training"][-1] == round(a["curve"]["disc"]["mean"][-1], 4)
    assert "factors (tmaze_5/floor): lr" in capsys.readouterr().out

    # a second field differs: reported, and refused under --one-factor
    c = _edited_copy(tmp_path / "b", tmp_path / "c", lambda r: r["config"].update(entropy_coeff=[0.05]))
    argv = ["--arm", f"a={tmp_path / 'a'}", "--arm", f"c={c}", "--what", "two"]
    assert probe_record.main(argv) == 0 and probe_record.main([*argv, "--one-factor"]) == 1
    captured = capsys.readouterr()
    assert "entropy_coeff, lr" in captured.out and "not a one-factor probe" in captured.err
    # a control and two arms, each one field away from it (not from each other): a one-factor probe
    d = _edited_copy(tmp_path / "a", tmp_path / "d", lambda r: r["config"].update(entropy_coeff=[0.05]))
    assert probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", f"b={tmp_path / 'b'}", "--arm", f"d={d}",
                              "--what", "two factors, one an arm", "--one-factor"]) == 0
    captured = capsys.readouterr()
    assert "entropy_coeff, lr" in captured.out and "not a one-factor probe" not in captured.err

    # one agent per arm, the agents differing: compared with --across-agents, the memory a factor
    other = _edited_copy(tmp_path / "a", tmp_path / "other",
                         lambda r: (r.update(agent="gru"), r["config"].update(memory="gru")))
    assert probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", f"g={other}", "--what", "memory",
                              "--across-agents", "--one-factor", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["factors"] == {"tmaze_5/floor|gru": ["memory"]} and set(record["arms"]) == {"a/floor|gru",
                                                                                                "g/floor|gru"}
    assert record["arms"]["g/floor|gru"]["disc"]["per_seed"] == a["disc"]["per_seed"]
    with pytest.raises(SystemExit) as e:  # two records in an arm: not one agent per arm
        probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", f"b={tmp_path / 'b'}", "--what", "x",
                           "--across-agents", "--arm", f"ab={_two_agents(tmp_path)}"])
    assert e.value.code == 2 and "one agent record per arm" in capsys.readouterr().err

    # bad input: one line, exit 2
    other = _edited_copy(tmp_path / "a", tmp_path / "ceil", lambda r: r.update(agent="ceiling"))
    (tmp_path / "empty").mkdir()
    for arms, message in (([f"a={tmp_path / 'a'}", f"o={other}"], "the arms hold different agents"),
                          ([f"a={tmp_path / 'a'}", f"e={tmp_path / 'empty'}"], "holds no agent records"),
                          ([f"a={tmp_path / 'a'}"], "give --arm twice"),
                          ([f"a={tmp_path / 'a'}", f"a={tmp_path / 'b'}"], "is given twice")):
        with pytest.raises(SystemExit) as e:
            probe_record.main([x for arm in arms for x in ("--arm", arm)] + ["--what", "x"])
        assert e.value.code == 2 and message in capsys.readouterr().err


def test_the_final_return_under_the_papers_smoothing():
    steps = list(range(100))
    cubic = [0.001 * t**3 - 0.1 * t**2 + 5 * t for t in steps]  # a cubic: Savitzky-Golay of order 3 keeps it exactly
    record = {"undisc": {"mean": 123.0}, "curve": {"env_step": steps, "undisc": {"mean": cubic}}}
    f = probe_record.final_by_definition(record, "undisc")
    assert f["final"] == 123.0 and f["last_bin"] == round(cubic[-1], 4)
    assert f["savgol"] == pytest.approx(cubic[-1], abs=1e-3)
    noisy = [c + (5.0 if t % 2 else -5.0) for t, c in zip(steps, cubic)]  # alternating noise is smoothed away
    record["curve"]["undisc"]["mean"] = noisy
    f = probe_record.final_by_definition(record, "undisc")
    assert f["last_bin"] == round(noisy[-1], 4) and abs(f["savgol"] - cubic[-1]) < 2.0
    # bins in which no episode ended (None in a record) are skipped; fewer bins than the window: no smoothed value
    record["curve"]["undisc"]["mean"] = [None if t % 2 else c for t, c in zip(steps, cubic)]
    assert probe_record.final_by_definition(record, "undisc")["savgol"] is not None
    record["curve"]["undisc"]["mean"] = [None] * 80 + cubic[:20]
    f = probe_record.final_by_definition(record, "undisc")
    assert f["savgol"] is None and f["last_bin"] == round(cubic[19], 4)


def test_tenths_of_training_skip_the_bins_in_which_no_episode_ended():
    # 1000-step episodes (HalfCheetah) leave the first bins of a short run empty (None): was a TypeError.
    curve = {"env_step": list(range(10, 110, 10)),
             "undisc": {"mean": [None, None, 1.0, None, 2.0, 3.0, None, 4.0, 5.0, None]}}
    assert probe_record.by_tenth(curve, "undisc") == [None, None, 1.0, 1.0, 2.0, 3.0, 3.0, 4.0, 5.0, 5.0]


@pytest.mark.slow  # 21 s on 2 cores: six small trainings
def test_train_runs_as_arms(tmp_path, capsys):
    """`pobax train --out` directories are arms too: one agent each, named as the benchmark names it, the curve from
    the metrics chunks where `metrics.csv` did not travel (`detached_queue.py --metrics` brings the chunks only)."""
    cfg = TrainConfig(env="tmaze_5", memory="memoryless", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2,
                      total_steps=4 * 16 * 4, num_seeds=2, num_chunks=2)
    train(cfg, tmp_path / "a", progress=False)
    train(dataclasses.replace(cfg, normalize_advantages=False), tmp_path / "b", progress=False)
    def record(path):  # without the time it was read at ("written", to the second)
        return {k: {f: v for f, v in r.items() if f != "written"} for k, r in probe_record.read_arm(path).items()}

    whole = record(tmp_path / "b")
    (tmp_path / "b" / "metrics.csv").unlink()
    assert record(tmp_path / "b") == whole  # the chunks give the curve metrics.csv gives
    out = tmp_path / "probe.json"
    assert probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", f"b={tmp_path / 'b'}", "--what", "std",
                              "--one-factor", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["factors"] == {"tmaze_5/floor": ["normalize_advantages"]}
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    arm = record["arms"]["b/floor"]
    assert arm["disc"]["per_seed"] == summary["sets"][0]["disc_return"]["per_seed"]
    assert arm["pobax_commit"] == summary["sessions"][0]["pobax_commit"] and len(arm["disc_by_tenth_of_training"]) == 10
    assert record["arms"]["a/floor"]["disc_by_tenth_of_training"][-1] is not None
    # bins in which no episode ended are null, as in a benchmark record (NaN is not JSON)
    train(dataclasses.replace(cfg, num_envs=1, num_steps=2, num_minibatches=1, total_steps=2 * 12, num_seeds=1,
                              num_chunks=1), tmp_path / "sparse", progress=False)
    (sparse,) = probe_record.read_arm(tmp_path / "sparse").values()
    assert None in sparse["curve"]["disc"]["mean"] and json.dumps(sparse, allow_nan=False)

    # the sets of one program as arms (DIR#N): each its own hyperparameters, returns and curve
    train(dataclasses.replace(cfg, lr=(2.5e-3, 2.5e-4)), tmp_path / "two", progress=False)
    assert probe_record.main(["--arm", f"x={tmp_path / 'two'}#0", "--arm", f"y={tmp_path / 'two'}#1", "--what", "lr",
                              "--one-factor", "--json", str(out)]) == 0
    record, two = json.loads(out.read_text()), json.loads((tmp_path / "two" / "summary.json").read_text())
    assert record["factors"] == {"tmaze_5/floor": ["lr"]}
    for i, name in enumerate(("x/floor", "y/floor")):
        assert record["arms"][name]["disc"]["per_seed"] == two["sets"][i]["disc_return"]["per_seed"]
        assert record["arms"][name]["auc"]["per_seed"] == two["sets"][i]["disc_return_auc"]["per_seed"]
    assert record["arms"]["x/floor"]["disc_by_tenth_of_training"] != record["arms"]["y/floor"][
        "disc_by_tenth_of_training"]  # each set's own curve

    # bad input, one line and exit 2: two sets in one run, unnamed or a set it did not train; a run whose summary was
    # edited; one cut short; a chunk of a finished run missing (its curve would cover part of training)
    shutil.copytree(tmp_path / "b", tmp_path / "gap")
    (tmp_path / "gap" / "metrics" / "00001.csv").unlink()
    summary["sets"][0]["disc_return"]["mean"] = 99.0
    (tmp_path / "b" / "summary.json").write_text(json.dumps(summary))
    train(cfg, tmp_path / "cut", progress=False, max_chunks=1)
    for arm, message in ((f"t={tmp_path / 'two'}", "trained 2 hyperparameter sets"),
                         (f"t={tmp_path / 'two'}#2", "has no hyperparameter set #2"),
                         (f"b={tmp_path / 'b'}", "was edited"), (f"c={tmp_path / 'cut'}", "has not finished"),
                         (f"g={tmp_path / 'gap'}", "or a chunk missing")):
        with pytest.raises(SystemExit) as e:
            probe_record.main(["--arm", f"a={tmp_path / 'a'}", "--arm", arm, "--what", "x"])
        assert e.value.code == 2 and message in capsys.readouterr().err


def test_one_record_of_a_table_as_an_arm(tmp_path, capsys):
    """A row of the shipped table (its record file) is an arm: the control of a probe that retrains one factor."""
    agents = Path(__file__).resolve().parents[1] / "results" / "agents" / "battleship_10"
    out = tmp_path / "probe.json"
    assert probe_record.main(["--arm", f"f={agents / 'floor.json'}", "--arm", f"g={agents / 'gru.json'}",
                              "--what", "x", "--across-agents", "--json", str(out)]) == 0
    record, floor = json.loads(out.read_text()), json.loads((agents / "floor.json").read_text())
    assert "memory" in record["factors"]["battleship_10/floor|gru"]
    assert record["arms"]["f/floor|gru"]["undisc"]["per_seed"] == floor["undisc"]["per_seed"]

    edited = tmp_path / "t" / "agents" / "battleship_10" / "floor.json"  # a record edited after it was written
    edited.parent.mkdir(parents=True)
    sealed = seal_record(floor)  # as pobax writes a record now
    edited.write_text(json.dumps({**sealed, "undisc": {**sealed["undisc"], "mean": 99.0}}))
    stray = tmp_path / "floor.json"  # a JSON file that is not in a benchmark's agents/ENV/
    stray.write_text(json.dumps(floor))
    for arm, message in ((f"e={edited}", "was edited after it was written"),
                         (f"s={stray}", "is not an agent record")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as e:
            probe_record.main(["--arm", f"f={agents / 'floor.json'}", "--arm", arm, "--what", "x"])
        assert e.value.code == 2 and message in capsys.readouterr().err


def test_json_over_a_file_it_did_not_write_or_a_directory_is_refused(tmp_path, capsys):
    """--json over notes.txt replaced it with the probe record; --json DIR printed the table, then a traceback."""
    agents = Path(__file__).resolve().parents[1] / "results" / "agents" / "battleship_10"
    arms = ["--arm", f"f={agents / 'floor.json'}", "--arm", f"g={agents / 'gru.json'}", "--what", "x",
            "--across-agents"]
    notes = tmp_path / "notes.txt"
    notes.write_text("precious")
    (tmp_path / "d").mkdir()
    for target, message in ((notes, "holds another file (not a probe record)"), (tmp_path / "d", "is a directory")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as e:
            probe_record.main([*arms, "--json", str(target)])
        out, err = capsys.readouterr()
        assert e.value.code == 2 and message in err and out == "", err
    assert notes.read_text() == "precious"
    again = tmp_path / "probe.json"  # a record it wrote is written again
    assert probe_record.main([*arms, "--json", str(again)]) == 0 and probe_record.main([*arms, "--json", str(again)]) == 0


@pytest.mark.parametrize("argv, message", [([], "the following arguments are required: --arm, --what"),
                                           (["--arm", "a=x", "--what", "w", "--jsn", "p"], "unrecognized arguments")])
def test_a_command_line_it_cannot_read_is_one_line_not_the_usage(capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        probe_record.main(argv)
    out, err = capsys.readouterr()
    assert e.value.code == 2 and out == "", err
    assert err.count("\n") == 1 and "usage:" not in err, err  # argparse's default: the usage block, then the error
    assert re.fullmatch(rf"(\S+): error: {message}.* \(see \1 --help\)\n", err), err
